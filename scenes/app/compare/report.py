"""One self-contained HTML page of a comparison (and diagnosis): what a person reads in a minute.

:func:`write_report` turns the result of :func:`scenes.app.compare.run_compare` (arrays included) and,
optionally, of :func:`scenes.app.compare.run_diagnose` into a single HTML file: every plot is a small PNG
embedded as base64 (no external file, script or style sheet), so the report can be mailed or archived
alone. The page opens with the verdict, then shows where and how the model fails:

verdict -> z residual map -> regions -> row/column profiles -> residual power spectrum -> distribution of
z (histogram, QQ) -> measured vs model ADU histograms -> global statistics (thesis Annex VII) ->
outlier counts -> stars -> streaks -> diagnosis candidates and the ledger of rounds.

Each section is one small function returning HTML (``""`` when its data are absent); a section that
fails on unexpected data is replaced by a one-line note, so the report of a long diagnosis is never lost
to one bad plot. The result may also be a JSON round trip of the full result (lists instead of arrays,
``None`` for NaN): every array is read through :func:`_arr`.

Plots use Matplotlib's Agg canvas directly (no pyplot state, no display needed).
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from detector.morphology import periodic_contrast
from detector.significance import DETECTION_SIGMA, STRONG_EVIDENCE

from .policy import DEFAULT_POLICY
from .statistics import PEAK_SIDE

#: resolution of the embedded plots [dots per inch]: small files, still legible
DPI = 72
#: colour scale limit of the z map [sigma]
Z_CLIP = 5.0
#: a region, row/column profile or outlier class is flagged when its excess is above this [sigma]
FLAG_SIGMA = DETECTION_SIGMA
#: Poisson deviance of an outlier count above which it is flagged (~3 sigma for one count)
DEVIANCE_FLAG = STRONG_EVIDENCE
#: misfit (a standardised excess [sigma]) below which the model explains the frame (noise-only frames give ~0-3):
#: the detection bar of a standardised excess, DETECTION_SIGMA
MISFIT_OK = DETECTION_SIGMA
#: candidates whose delta BIC is at or above this are not significant (DESIGN.md contract)
SIGNIFICANT_DELTA_BIC = DEFAULT_POLICY.significant_delta_bic

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;max-width:1000px;margin:1.5em auto;
     padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.4em;margin-bottom:.2em} h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
.meta{color:#666;font-size:.85em} nav{font-size:.85em;margin:.8em 0} nav a{margin-right:.7em}
.verdict{border:2px solid;border-radius:6px;padding:.6em 1em;margin:1em 0}
.verdict.ok{border-color:#2a7;background:#eefaf3} .verdict.warn{border-color:#d90;background:#fff8e6}
.verdict.bad{border-color:#c33;background:#fdeeee} .verdict p{margin:.3em 0}
.verdict .headline{font-size:1.1em;font-weight:600}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0} th,td{border:1px solid #ddd;padding:2px 6px}
th{background:#f3f3f3;text-align:left} td.num{text-align:right;font-variant-numeric:tabular-nums}
tr.flag td{background:#fde8e8} tr.sig td{background:#e8f6ee}
figure{margin:.5em 0} figure img{max-width:100%} figcaption{font-size:.8em;color:#555}
.note{font-size:.85em;color:#666} .problem{color:#a00;font-size:.85em}
"""


# --- small helpers ---------------------------------------------------------------------------------------------

def _arr(x) -> np.ndarray:
    """Any array-like (numpy, list from JSON with None for NaN) as a float array; empty when absent."""
    if x is None:
        return np.zeros(0)
    try:
        return np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        return np.zeros(0)


def _num(x) -> float:
    """A scalar as float, NaN when absent or not a number."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v


def _fmt(x, digits: int = 4) -> str:
    """A number for a table cell: ``digits`` significant digits, 'n/a' for None/NaN."""
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    v = _num(x)
    if not math.isfinite(v):
        return "n/a"
    return f"{v:.{digits}g}"


def _e(text) -> str:
    return html.escape(str(text))


def _clean_name(name) -> str:
    """A source name for display (bytes decoded, a stray ``b'...'`` repr unwrapped)."""
    if isinstance(name, bytes):
        name = name.decode(errors="replace")
    s = str(name).strip()
    if len(s) >= 3 and s[:2] in ("b'", 'b"') and s[-1] == s[1]:
        s = s[2:-1]
    return s


def _table(header: list[str], rows: list[list], numeric: set[int] | None = None,
           row_class: list[str] | None = None, digits: int = 4) -> str:
    """An HTML table; cells are escaped; columns in ``numeric`` are right-aligned and formatted."""
    numeric = numeric or set()
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in header), "</tr></thead><tbody>"]
    for i, row in enumerate(rows):
        cls = f' class="{row_class[i]}"' if row_class and row_class[i] else ""
        cells = [f'<td class="num">{_e(_fmt(c, digits))}</td>' if j in numeric else f"<td>{_e(c)}</td>"
                 for j, c in enumerate(row)]
        out.append(f"<tr{cls}>{''.join(cells)}</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _figure(ncols: int = 1, nrows: int = 1, width: float = 9.0, height: float = 3.2):
    """A Matplotlib figure on the Agg canvas (no pyplot) and its axes as a flat list."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, list(axes.ravel())


def _png(fig) -> str:
    """The figure as a base64 PNG ``<img>``."""
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=DPI)
    data = base64.b64encode(_palette_png(buf.getvalue())).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="plot">'


def _palette_png(raw: bytes) -> bytes:
    """The PNG re-encoded with a 256-colour palette (a quarter of the size, no visible loss for plots)."""
    try:
        from PIL import Image

        out = io.BytesIO()
        Image.open(io.BytesIO(raw)).convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(
            out, format="PNG", optimize=True)
        return out.getvalue()
    except Exception:  # noqa: BLE001  (Pillow missing or too old: keep Matplotlib's own PNG)
        return raw


def _fig_html(fig, caption: str) -> str:
    return f"<figure>{_png(fig)}<figcaption>{caption}</figcaption></figure>"


def _png_file(path) -> str | None:
    """An existing PNG file as an embedded ``<img>`` (None when absent or unreadable)."""
    try:
        data = Path(path).read_bytes()
    except (OSError, TypeError):
        return None
    if not data.startswith(b"\x89PNG"):
        return None
    return f'<img src="data:image/png;base64,{base64.b64encode(data).decode("ascii")}" alt="ledger">'


def _section(anchor: str, title: str, body: str) -> str:
    return f'<section id="{anchor}"><h2>{_e(title)}</h2>{body}</section>'


def _excess_sigma(chi2_per_dof, n) -> float:
    """How many standard deviations chi2/dof lies above 1 for ``n`` degrees of freedom."""
    c, n = _num(chi2_per_dof), _num(n)
    if not (math.isfinite(c) and math.isfinite(n)) or n <= 0:
        return float("nan")
    return (c - 1.0) / math.sqrt(2.0 / n)


def _positive(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points with x > 0, y > 0 and finite (for log-log axes)."""
    n = min(x.size, y.size)
    x, y = x[:n], y[:n]
    ok = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    return x[ok], y[ok]


# --- the verdict -------------------------------------------------------------------------------------------------

def reading(result: dict) -> tuple[str, str]:
    """A plain-words reading of chi2/dof and misfit: (sentence, level 'ok' | 'warn' | 'bad')."""
    chi2 = _num(result.get("chi2_per_dof"))
    misfit = _num(result.get("misfit"))
    n = result.get("n_compared")
    sig = _excess_sigma(chi2, n)
    if not math.isfinite(chi2) or (n is not None and _num(n) == 0):
        msg = ("No pixel could be compared pixel by pixel (all saturated, flagged or outliers): chi2/dof and "
               "misfit say nothing about this frame.")
        return msg, "bad"
    sig_txt = f" ({sig:+.1f} sigma from 1)" if math.isfinite(sig) else ""
    if math.isfinite(sig) and sig < -FLAG_SIGMA:
        return ("The residuals are smaller than the model's noise" + sig_txt + ": the noise model (read noise, "
                "gain, PRNU/DSNU or row-noise variance) is too large for this camera.", "warn")
    if math.isfinite(sig) and sig > FLAG_SIGMA:
        level = "bad" if chi2 > 1.5 or (math.isfinite(misfit) and misfit > 10 * MISFIT_OK) else "warn"
        return ("The model misses something: the pixel residuals exceed the model's noise" + sig_txt +
                ". See the z map and the worst regions below for where, the profiles and spectrum for what.",
                level)
    if math.isfinite(misfit) and misfit > MISFIT_OK:
        return ("Pixel by pixel the residuals look like noise" + sig_txt + ", but the outlier counts or the "
                "row/column structure depart from the model (misfit " + _fmt(misfit, 3) + "): see the "
                "outlier table and the profiles.", "warn" if misfit < 10 * MISFIT_OK else "bad")
    return ("The model explains the frame: the residuals are consistent with the model's own noise" + sig_txt
            + ".", "ok")


def _worst_regions_html(result: dict) -> str:
    regions = result.get("regions") or {}
    worst = result.get("worst_regions") or sorted(regions, key=lambda r: -_num(regions[r].get("chi2_per_dof")))[:3]
    parts = []
    for name in worst:
        r = regions.get(name, {})
        parts.append(f"{_e(name)} (chi2/dof {_e(_fmt(r.get('chi2_per_dof')))}, mean z {_e(_fmt(r.get('mean_z'), 3))})")
    return "<p>Largest residuals: " + "; ".join(parts) + ".</p>" if parts else ""


_LEVEL_WORDS = {"light_scale": "light", "background_scale": "background", "offset_adu": "bias offset",
                "dark_scale": "dark"}


def _level_words(name: str, coef: float, delta_adu: float | None) -> str:
    """One refitted level in words: the bias offset in ADU; a light, background or dark level as the factor
    on the model's level with the change it makes at the mean pixel [ADU] (a percentage of a level near zero,
    e.g. the dark signal of a short exposure, says nothing: "x -106 [-0.8 ADU at the mean pixel]" does)."""
    word = _LEVEL_WORDS.get(name, name)
    if name == "offset_adu":
        return f"{word} {coef:+.2f} ADU"
    text = f"{word} x {1 + coef:.4g}"
    if delta_adu is not None and math.isfinite(_num(delta_adu)):
        text += f" [{_num(delta_adu):+.3g} ADU at the mean pixel]"
    return text


def _levels_text(result: dict) -> str:
    """chi2/dof with the global levels refitted, and the fitted levels in words ('' when absent)."""
    chi2 = _num(result.get("chi2_per_dof_levels"))
    if not math.isfinite(chi2):
        return ""
    levels = result.get("levels") or {}
    parts = [_level_words(k, _num(v), (result.get("levels_adu") or {}).get(k)) for k, v in levels.items()]
    return (f"With the global levels refitted: chi2/dof = {_fmt(chi2)}" +
            (f" ({', '.join(parts)})" if parts else "") + ".")


def section_verdict(result: dict, diagnosis: dict | None) -> str:
    """The box at the top: the diagnosis verdict (or the plain-words reading), chi2/dof, misfit, worst regions."""
    text, level = reading(result)
    chi2 = result.get("chi2_per_dof") if _num(result.get("n_compared")) != 0 else None
    head = (f"chi2/dof = {_fmt(chi2)} over {_fmt(result.get('n_compared'))} pixels "
            f"({_fmt(result.get('n_statistical'))} compared statistically); misfit = {_fmt(result.get('misfit'), 3)}")
    body = [f'<p class="headline">{_e(head)}</p>']
    if chi2 is not None and _levels_text(result):
        body.append(f"<p>{_e(_levels_text(result))}</p>")
    if diagnosis is not None:
        sig = [c for c in diagnosis.get("candidates", []) if c.get("significant")]
        if sig:
            level = "bad"
        verdict = diagnosis.get("verdict") or ("no missing effect was found" if not sig else sig[0]["effect"])
        body.append(f"<p><b>Diagnosis:</b> {_e(verdict)}.</p>")
        applied = diagnosis.get("applied")
        if applied:
            body.append(f"<p>Applied: the scene with <code>[effects.{_e(applied.get('effect'))}]</code> added was "
                        f"written to <code>{_e(applied.get('scene'))}</code>.</p>")
    body.append(f"<p>{_e(text)}</p>")
    body.append(_worst_regions_html(result))
    warnings = (result.get("summary") or {}).get("warnings") or []
    if warnings:
        body.append("<p class=\"problem\">Warnings: " + "; ".join(_e(w) for w in warnings) + "</p>")
    return f'<div class="verdict {level}">{"".join(body)}</div>'


# --- residual map, regions, profiles ------------------------------------------------------------------------------

def section_zmap(result: dict) -> str:
    z = _arr(result.get("z_map"))
    if z.ndim != 2 or z.size == 0:
        return ""
    import matplotlib

    k = result.get("z_map_block", 1)
    fig, (ax,) = _figure(width=6.4, height=5.2)
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.6")
    im = ax.imshow(np.ma.masked_invalid(z), origin="lower", cmap=cmap, vmin=-Z_CLIP, vmax=Z_CLIP,
                   interpolation="nearest", extent=(0, z.shape[1] * k, 0, z.shape[0] * k))
    ax.set_xlabel("column [px]")
    ax.set_ylabel("row [px]")
    fig.colorbar(im, ax=ax, label="z = (data - model) / sigma_model", shrink=0.85)
    cap = (f"Normalised residual z, block mean of {k} x {k} pixels (block size {k}), rescaled by {k} so that "
           f"white noise keeps unit variance; colour clipped at +-{Z_CLIP:g}. Pixels compared only statistically "
           "(spikes, outlier columns, saturation) count as 0. Red: data above the model.")
    return _section("zmap", "Residual map", _fig_html(fig, _e(cap)))


def section_regions(result: dict) -> str:
    regions = result.get("regions") or {}
    if not regions:
        return ""
    rows, cls = [], []
    for name, r in regions.items():
        rows.append([name, r.get("n"), r.get("chi2_per_dof"), r.get("mean_z"), r.get("mean_residual_adu"),
                     r.get("data_mean_adu"), r.get("model_mean_adu")])
        cls.append("flag" if _excess_sigma(r.get("chi2_per_dof"), r.get("n")) > FLAG_SIGMA else "")
    tab = _table(["region", "pixels", "chi2/dof", "mean z", "mean residual [ADU]", "data mean [ADU]",
                  "model mean [ADU]"], rows, numeric={1, 2, 3, 4, 5, 6}, row_class=cls, digits=5)
    note = (f'<p class="note">Rows upward, columns rightward; radial_0 is the centre, radial_4 the corners. '
            f"Highlighted: chi2/dof more than {FLAG_SIGMA:g} sigma above 1 (sigma = sqrt(2/n)).</p>")
    return _section("regions", "Regions", tab + note)


def section_profiles(result: dict) -> str:
    prof = result.get("profiles") or {}
    if not any(_arr((prof.get(k) or {}).get("mean_residual_adu")).size for k in ("row", "column")):
        return ""
    fig, axes = _figure(2, 2, width=9.0, height=4.6)
    for j, key in enumerate(("row", "column")):
        p = prof.get(key) or {}
        mean, z = _arr(p.get("mean_residual_adu")), _arr(p.get("z"))
        idx = np.arange(mean.size)
        axes[j].plot(idx, mean, lw=0.7, color="C0")
        axes[j].axhline(0, color="grey", lw=0.6)
        axes[j].set_ylabel("mean residual [ADU]")
        axes[j].set_title(f"per {key}: chi2/dof {_fmt(p.get('chi2_per_dof'))}", fontsize=9)
        axes[2 + j].plot(np.arange(z.size), z, lw=0.7, color="C1")
        for s in (-3, 3):
            axes[2 + j].axhline(s, color="grey", lw=0.6, ls="--")
        axes[2 + j].set_ylabel("z of the mean")
        axes[2 + j].set_xlabel(key)
    cap = ("Mean residual (data - model) of each row and each column over the pixels compared pixel by pixel "
           "(top), and the same in units of its standard error (bottom; dashed: +-3). Noise gives chi2/dof ~1; "
           "row noise, bias structure or column defects raise it.")
    return _section("profiles", "Row and column profiles", _fig_html(fig, _e(cap)))


def section_power(result: dict) -> str:
    pw = result.get("power") or {}
    curves = [("radial", pw.get("freq"), pw.get("radial")), ("along rows (per-row means)", pw.get("row_freq"),
              pw.get("row_power")), ("along columns (per-column means)", pw.get("col_freq"), pw.get("col_power"))]
    curves = [(t, *_positive(_arr(f), _arr(p))) for t, f, p in curves]
    if not any(f.size for _, f, _ in curves):
        return ""
    fig, axes = _figure(3, 1, width=9.6, height=3.0)
    for ax, (title, f, p) in zip(axes, curves):
        if f.size:
            ax.loglog(f, p, lw=0.9, marker="." if f.size < 60 else None, ms=3)
        ax.axhline(1.0, color="C3", lw=0.8, ls="--", label="white noise")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("frequency [cycles / map pixel]")
    axes[0].set_ylabel("power of z")
    axes[0].legend(fontsize=7)
    k = result.get("z_map_block", 1)
    cap = (f"Power spectrum of the z map (one map pixel = {k} x {k} pixels), normalised so that white noise is "
           "flat at 1 (dashed). Power rising at low frequency: large-scale structure (gradients, glow, vignetting, "
           "straylight); peaks: periodic patterns.")
    return _section("power", "Residual power spectrum", _fig_html(fig, _e(cap)) + _peaks_html(result))


def _peaks_html(result: dict, shown: int = 3) -> str:
    """The strongest peaks of the full-resolution spectrum as a small table ('' when absent)."""
    pk = result.get("power_peaks") or {}
    peaks = [p for p in (pk.get("peaks") or []) if isinstance(p, dict)][:shown]
    if not peaks:
        return ""
    rows = [[p.get("fx"), p.get("fy"), p.get("power_ratio")] for p in peaks]
    side = pk.get("side")
    # a peak is flagged above the morphology's bar of a spectral line significant on its own among the cut's
    # frequencies (white noise tops out at ~15-25 x the median); a result without the side: the default cut's
    k = int(_num(side)) if np.isfinite(_num(side)) else PEAK_SIDE
    flag = periodic_contrast(k * (k // 2 + 1))
    cls = ["flag" if _num(p.get("power_ratio")) > flag else "" for p in peaks]
    tab = _table(["fx [cycles/px]", "fy [cycles/px]", "power / median"], rows, numeric={0, 1, 2}, row_class=cls,
                 digits=3)
    note = (f'<p class="note">Strongest peaks of the full-resolution spectrum of z (central {_e(side)} x {_e(side)} '
            "pixels, sources and pixels not compared set to 0). White noise tops out at ~15-25 x the median "
            f"(highlighted above {flag:.3g}). (0.5, 0.5): a 2 x 2 pattern such as a Bayer mosaic; (0.5, 0) or "
            "(0, 0.5): alternate columns or rows.</p>")
    return tab + note


# --- distributions and statistics -----------------------------------------------------------------------------------

def section_distribution(result: dict) -> str:
    d = result.get("distribution") or {}
    edges, hist = _arr(d.get("z_edges")), _arr(d.get("z_hist"))
    qn, qz = _arr(d.get("qq_normal")), _arr(d.get("qq_z"))
    if hist.size == 0 and qz.size == 0:
        return ""
    fig, (a0, a1) = _figure(2, 1, width=9.0, height=3.2)
    if hist.size and edges.size == hist.size + 1 and np.nansum(hist) > 0:
        width = np.diff(edges)
        dens = hist / (np.nansum(hist) * width)
        centres = 0.5 * (edges[1:] + edges[:-1])
        a0.step(centres, np.where(dens > 0, dens, np.nan), where="mid", label="z of the data")
        xs = np.linspace(edges[0], edges[-1], 400)
        a0.plot(xs, np.exp(-0.5 * xs * xs) / np.sqrt(2 * np.pi), "k--", lw=0.8, label="unit normal")
        a0.set_yscale("log")
        a0.set_ylim(max(0.5 / max(np.nansum(hist), 1), 1e-9), 1)
        a0.set_xlabel("z")
        a0.set_ylabel("density")
        a0.legend(fontsize=7)
    if qz.size and qz.size == qn.size:
        a1.plot(qn, qz, ".", ms=3)
        lim = np.nanmax(np.abs(np.concatenate([qn, qz]))) if np.isfinite(qz).any() else 3
        a1.plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        a1.set_xlabel("unit-normal quantile")
        a1.set_ylabel("quantile of z")
        a1.set_title("QQ plot (0.1 % .. 99.9 %)", fontsize=9)
    cap = (f"Distribution of z over the pixels compared pixel by pixel: skew {_fmt(d.get('skew'), 3)}, excess "
           f"kurtosis {_fmt(d.get('kurtosis'), 3)} (0 and 0 for Gaussian noise). Wider than the normal: variance "
           "missing from the model (PRNU, DSNU, row noise); heavy tails: unmodelled outliers.")
    return _section("distribution", "Distribution of the residuals", _fig_html(fig, _e(cap)))


def section_adu_hist(result: dict) -> str:
    d = result.get("distribution") or {}
    edges, dh, mh = _arr(d.get("adu_edges")), _arr(d.get("data_hist")), _arr(d.get("model_hist"))
    if dh.size == 0 or edges.size != dh.size + 1:
        return ""
    centres = 0.5 * (edges[1:] + edges[:-1])
    fig, (ax,) = _figure(width=7.0, height=3.0)
    ax.step(centres, np.where(dh > 0, dh, np.nan), where="mid", label="measured")
    if mh.size == dh.size:
        ax.step(centres, np.where(mh > 0, mh, np.nan), where="mid", label="model realisation", alpha=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("ADU")
    ax.set_ylabel("pixels")
    ax.legend(fontsize=7)
    cap = ("Histogram of the measured frame and of one noisy realisation of the model (fixed seed), between the "
           "0.1 and 99.9 percentiles of the data.")
    return _section("adu", "Measured vs model ADU", _fig_html(fig, _e(cap)))


_STAT_ROWS = (("median", "median"), ("mean", "mean"), ("std", "std"), ("robust_std", "robust std (1.4826 MAD)"),
              ("min", "min"), ("max", "max"))


def section_global_stats(result: dict) -> str:
    m, r, mm = (v if isinstance(v, dict) else {} for v in (result.get(k) for k in ("measured", "model", "model_mean")))
    if not m and not r:
        return ""
    rows = [[label, m.get(k), r.get(k), mm.get(k), _num(m.get(k)) - _num(r.get(k))] for k, label in _STAT_ROWS
            if k in m or k in r]
    tab = _table(["statistic [ADU]", "measured", "model (realisation)", "model mean (noiseless)",
                  "measured - model"], rows, numeric={1, 2, 3, 4}, digits=6)
    note = ('<p class="note">The thesis\'s Annex VII columns. "model" is one noisy realisation of the scene '
            "(fixed seed), directly comparable with the measurement; the mean frame has no noise, so its std "
            "is the spread of the signal alone.</p>")
    return _section("stats", "Global statistics", tab + note)


_OUTLIER_LABELS = {"single_pos": "isolated positive spikes (hot/warm pixels)",
                   "cluster_pos": "connected positive spikes (cosmic-ray tracks)",
                   "single_neg": "isolated negative spikes (dead pixels)",
                   "hot_cols": "columns above their neighbours (hot columns)",
                   "cold_cols": "columns below their neighbours (cold columns)",
                   "strong_neg": "groups of dark pixels beyond the noise (dead pixels, dead clusters)",
                   "tracks": "thin groups of bright pixels beyond the noise (particle tracks)"}


def section_outliers(result: dict) -> str:
    out = result.get("outliers") or {}
    if not out:
        return ""
    rows, cls = [], []
    for k, v in out.items():
        rows.append([_OUTLIER_LABELS.get(k, k), v.get("data"), v.get("model"), v.get("deviance")])
        cls.append("flag" if _num(v.get("deviance")) > DEVIANCE_FLAG else "")
    tab = _table(["outlier class", "measured", "model (one realisation)", "deviance"], rows, numeric={1, 2, 3},
                 row_class=cls)
    note = ('<p class="note">Pixels the model can only predict statistically are compared by their counts with '
            "those of one noisy realisation of the model. Both counts are Poisson, so the deviance is the "
            "likelihood ratio of two Poisson samples, 2[o ln(2o/(o+m)) + m ln(2m/(o+m))], ~1 when the rates agree "
            f"(highlighted above {DEVIANCE_FLAG:g}).</p>")
    return _section("outliers", "Outlier counts", tab + note)


# --- sources -----------------------------------------------------------------------------------------------------

def section_stars(result: dict) -> str:
    st = result.get("stars") or {}
    if not st or not st.get("n"):
        return ""
    mag, x, y = _arr(st.get("mag")), _arr(st.get("x")), _arr(st.get("y"))
    ratio, err, rf = _arr(st.get("flux_ratio")), _arr(st.get("flux_ratio_err")), _arr(st.get("r_field"))
    dx, dy = _arr(st.get("dx_px")), _arr(st.get("dy_px"))
    sd, sm = _arr(st.get("size_data_px")), _arr(st.get("size_model_px"))
    summary = (f"{st.get('n')} catalogue stars measured: median flux ratio data/model "
               f"{_fmt(st.get('median_flux_ratio'))}, median centroid offset {_fmt(st.get('median_offset_px'), 3)} px, "
               f"median size ratio {_fmt(st.get('median_size_ratio'))}")
    if ratio.size == 0:
        return _section("stars", "Stars", f"<p>{_e(summary)}.</p>")
    fig, axes = _figure(2, 2, width=9.0, height=6.4)
    yerr = err if err.size == ratio.size else None
    if mag.size == ratio.size and np.isfinite(mag).any():
        axes[0].errorbar(mag, ratio, yerr=yerr, fmt=".", ms=4, lw=0.7)
    else:
        axes[0].text(0.5, 0.5, "no magnitudes", ha="center", transform=axes[0].transAxes)
    axes[0].set_xlabel("magnitude")
    axes[0].set_ylabel("flux data / model")
    if rf.size == ratio.size:
        axes[1].errorbar(rf, ratio, yerr=yerr, fmt=".", ms=4, lw=0.7)
    axes[1].set_xlabel("field radius (0 centre, 1 corner)")
    axes[1].set_ylabel("flux data / model")
    for a in axes[:2]:
        a.axhline(1.0, color="grey", lw=0.7, ls="--")
    off = np.hypot(dx, dy)
    med = float(np.nanmedian(off)) if off.size and np.isfinite(off).any() else 0.0
    z = _arr(result.get("z_map"))
    k = result.get("z_map_block", 1)
    span = max(z.shape) * k if z.ndim == 2 and z.size else max(np.nanmax(x, initial=1), np.nanmax(y, initial=1))
    gain = _arrow_gain(0.05 * span / max(med, 1e-6))
    if dx.size == x.size and dy.size == y.size:
        axes[2].quiver(x, y, dx * gain, dy * gain, angles="xy", scale_units="xy", scale=1, width=0.004)
        axes[2].plot(x, y, ".", ms=2, color="grey")
    if z.ndim == 2 and z.size:
        axes[2].set_xlim(0, z.shape[1] * k)
        axes[2].set_ylim(0, z.shape[0] * k)
    axes[2].set_aspect("equal", adjustable="box")
    axes[2].set_title(f"centroid offset data - model, arrows x{gain:g}", fontsize=9)
    axes[2].set_xlabel("column [px]")
    axes[2].set_ylabel("row [px]")
    if rf.size == sd.size == sm.size and sd.size:
        with np.errstate(invalid="ignore", divide="ignore"):
            axes[3].plot(rf, sd / sm, ".", ms=4)
    axes[3].axhline(1.0, color="grey", lw=0.7, ls="--")
    axes[3].set_xlabel("field radius (0 centre, 1 corner)")
    axes[3].set_ylabel("size data / model (sigma)")
    slopes = [f"flux-ratio slope vs radius {_fmt(st.get('flux_ratio_vs_radius_slope'), 3)}"
              if "flux_ratio_vs_radius_slope" in st else "",
              f"vs magnitude {_fmt(st.get('flux_ratio_vs_mag_slope'), 3)} per mag"
              if "flux_ratio_vs_mag_slope" in st else ""]
    for a in (axes[0], axes[1], axes[3]):
        a.ticklabel_format(axis="y", useOffset=False)
    cap = (summary + (". " + ", ".join(s for s in slopes if s) if any(slopes) else "") +
           ". Aperture photometry (radius 4 px), the model's whole background (sky included) subtracted. A ratio falling with radius: "
           "vignetting; with magnitude: nonlinearity or a wrong zero point; sizes growing with radius: "
           "coma/field PSF; common offsets: a pointing/WCS error, radial ones: distortion.")
    return _section("stars", "Stars", _fig_html(fig, _e(cap)))


def _arrow_gain(g: float, cap: float = 1000.0) -> float:
    """A round magnification (1, 2, 5 x 10^n) at most ``g`` and ``cap``, at least 1."""
    g = min(max(g, 1.0), cap)
    e = 10.0 ** math.floor(math.log10(g))
    return max(m * e for m in (1, 2, 5) if m * e <= g)


def section_streaks(result: dict) -> str:
    streaks = [s for s in (result.get("streaks") or []) if s]
    if not streaks:
        return ""
    rows = [[_clean_name(s.get("name")), s.get("length_px"), s.get("total_flux_ratio")] for s in streaks]
    tab = _table(["object", "length [px]", "flux data / model"], rows, numeric={1, 2})
    shown = streaks[:10]
    fig, (a0, a1) = _figure(2, 1, width=9.0, height=3.0)
    for i, s in enumerate(shown):
        fr, off = _arr(s.get("flux_ratio")), _arr(s.get("offset_px"))
        n = max(fr.size, 1)
        pos = (np.arange(fr.size) + 0.5) / n * _num(s.get("length_px"))
        label = _clean_name(s.get("name")) or f"object {i}"
        a0.plot(pos, fr, ".-", ms=4, lw=0.8, label=label)
        if off.size == fr.size:
            a1.plot(pos, off, ".-", ms=4, lw=0.8, label=label)
    a0.axhline(1.0, color="grey", lw=0.7, ls="--")
    a1.axhline(0.0, color="grey", lw=0.7, ls="--")
    a0.set_ylabel("flux data / model")
    a1.set_ylabel("cross-track offset [px]")
    for a in (a0, a1):
        a.set_xlabel("along the track [px]")
    a0.legend(fontsize=7)
    for a in (a0, a1):
        a.ticklabel_format(axis="y", useOffset=False)
    cap = ("Along each streak (from its start to its end, in equal segments): flux of the data over the model's, "
           "and the cross-track centroid offset. A trend in flux: wrong brightness law or shutter timing; a "
           "trend in offset: wrong rate or direction." + (f" First {len(shown)} of {len(streaks)} shown."
                                                            if len(streaks) > len(shown) else ""))
    return _section("streaks", "Streaks", tab + _fig_html(fig, _e(cap)))


# --- the diagnosis ------------------------------------------------------------------------------------------------

def _params_text(params) -> str:
    if not isinstance(params, dict):
        return "" if params is None else str(params)
    return ", ".join(f"{k}={_fmt(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v}"
                     for k, v in params.items())


def section_candidates(diagnosis: dict | None) -> str:
    if diagnosis is None:
        return ""
    cands = diagnosis.get("candidates") or []
    parts = []
    if cands:
        rows = [[i + 1, c.get("effect"), c.get("delta_bic"), c.get("chi2_per_dof"),
                 "yes" if c.get("significant") else ("rejected" if c.get("rejected") else "no"),
                 c.get("explanation", "") + (f" (rejected: {c['rejected']})" if c.get("rejected") else ""),
                 _params_text(c.get("params"))]
                for i, c in enumerate(cands)]
        cls = ["sig" if c.get("significant") else "" for c in cands]
        parts.append(_table(["#", "effect", "delta BIC", "chi2/dof after", "significant", "explanation", "params"],
                            rows, numeric={0, 2, 3}, row_class=cls))
    else:
        parts.append("<p>No effect could be fitted.</p>")
    base = diagnosis.get("baseline") or {}
    parts.append(f'<p class="note">Baseline chi2/dof {_e(_fmt(base.get("chi2_per_dof")))}. Each absent effect is '
                 "fitted to the residuals under the model's noise and ranked by delta BIC = delta(-2 ln L) + k ln n; "
                 f"a candidate is significant when delta BIC &lt; {SIGNIFICANT_DELTA_BIC:g} (highlighted). "
                 "chi2/dof after: with the fitted effect in the model and the global levels refitted (compare "
                 "with the baseline's chi2/dof with levels refitted). A candidate that only adds noise and brings "
                 "chi2/dof far below 1 is rejected: it absorbs a residual pattern, it does not explain it.</p>")
    problems = diagnosis.get("problems") or []
    if problems:
        items = "".join(f"<li><code>{_e(p.get('effect'))}</code>: {_e(p.get('error'))}</li>" for p in problems)
        parts.append(f'<p class="problem">Effects whose signature failed (skipped):</p>'
                     f'<ul class="problem">{items}</ul>')
    return _section("diagnosis", "Diagnosis: candidate effects", "".join(parts))


def section_ledger(diagnosis: dict | None) -> str:
    led = (diagnosis or {}).get("ledger") or {}
    rounds = led.get("rounds") or []
    if not rounds and not led.get("plot"):
        return ""
    parts = []
    img = _png_file(led["plot"]) if led.get("plot") else None
    if img:
        parts.append(f"<figure>{img}<figcaption>chi2/dof and misfit round by round; each point labelled with the "
                     "effect added after it.</figcaption></figure>")
    if rounds:
        rows = [[r.get("round"), r.get("scene"), r.get("chi2_per_dof"), r.get("misfit"), r.get("applied") or "",
                 r.get("delta_bic")] for r in rounds]
        parts.append(_table(["round", "scene", "chi2/dof", "misfit", "applied", "delta BIC"], rows,
                            numeric={0, 2, 3, 5}))
    if led.get("path"):
        parts.append(f'<p class="note">Ledger: <code>{_e(led["path"])}</code></p>')
    return _section("ledger", "Ledger of rounds", "".join(parts))


# --- the page ------------------------------------------------------------------------------------------------------

_NAV = (("zmap", "map"), ("regions", "regions"), ("profiles", "profiles"), ("power", "spectrum"),
        ("distribution", "z distribution"), ("adu", "ADU"), ("stats", "statistics"), ("outliers", "outliers"),
        ("stars", "stars"), ("streaks", "streaks"), ("diagnosis", "diagnosis"), ("ledger", "ledger"))


def _safe(fn: Callable[..., str], *args) -> str:
    """A section, or a one-line note when it fails on unexpected data (the report is still written)."""
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001  (one bad section must not lose the whole report)
        name = fn.__name__.removeprefix("section_")
        return f'<p class="problem">Section "{_e(name)}" could not be drawn: {_e(type(exc).__name__)}: {_e(exc)}</p>'


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("newtsim")
    except Exception:  # noqa: BLE001
        return "?"


def _files(result: dict) -> tuple[str | None, str | None]:
    """The scene and measured file names recorded in the summary (if any)."""
    summ = result.get("summary") or {}
    out = []
    for key in ("scene", "measured"):
        v = summ.get(f"{key}_file", summ.get(key))
        out.append(str(v) if isinstance(v, (str, Path)) else None)
    return out[0], out[1]


def render_html(result: dict, *, diagnosis: dict | None = None, title: str | None = None) -> str:
    """The report as one HTML string (see :func:`write_report`)."""
    scene, measured = _files(result)
    if title is None:
        what = "diagnose" if diagnosis is not None else "compare"
        title = f"newtsim {what}: {Path(scene or 'scene').name} vs {Path(measured or 'measured frame').name}"
    sections = [_safe(section_zmap, result), _safe(section_regions, result), _safe(section_profiles, result),
                _safe(section_power, result), _safe(section_distribution, result), _safe(section_adu_hist, result),
                _safe(section_global_stats, result), _safe(section_outliers, result), _safe(section_stars, result),
                _safe(section_streaks, result), _safe(section_candidates, diagnosis), _safe(section_ledger, diagnosis)]
    body = "".join(sections)
    nav = " ".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in _NAV if f'id="{a}"' in body)
    meta = [f"scene <code>{_e(scene)}</code>" if scene else "",
            f"measured <code>{_e(measured)}</code>" if measured else "",
            f"newtsim {_e(_version())}", _dt.datetime.now().isoformat(timespec="seconds")]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>"
            f"<h1>{_e(title)}</h1><p class=\"meta\">{' | '.join(m for m in meta if m)}</p>"
            f"{_safe(section_verdict, result, diagnosis)}<nav>{nav}</nav>{body}</body></html>\n")


def write_report(result: dict, path, *, diagnosis: dict | None = None, title: str | None = None) -> Path:
    """Write the comparison (and diagnosis) as ONE self-contained HTML file; return its path.

    Parameters
    ----------
    result : dict
        :func:`scenes.app.compare.run_compare` output (arrays included; a JSON round trip of it works too).
    path : str or Path
        The HTML file to write (its folder must exist).
    diagnosis : dict, optional
        :func:`scenes.app.compare.run_diagnose` output (``verdict``, ``candidates``, ``problems``, ``ledger``).
    title : str, optional
        Page title (default: the scene and measured file names).
    """
    from detector.errors import DetectorError

    p = Path(path)
    text = render_html(result, diagnosis=diagnosis, title=title)
    try:
        p.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise DetectorError(f"cannot write the report ({exc.strerror or exc})", file=str(p),
                            expected="a writable file in an existing folder") from None
    return p
