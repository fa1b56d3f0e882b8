"""The per-star table of a comparison (the ``star_table`` of the compare JSON).

For every catalogue star of the model's TRUTH table inside the frame (brightest first, at most ``max_rows``):
position [px], catalogue magnitude, the model's flux and the measured flux in a circular aperture [ADU], both
with the model's background (sky, dark, bias through the chain) subtracted, their ratio and its 1-sigma error
(from the model's variance), the centroid offset data - model [px] and the Gaussian-equivalent sizes
(second-moment sigma [px]) of both. A star with a masked, non-finite or saturated pixel in its aperture is
listed with ``flag`` saying so and no ratio.
"""

from __future__ import annotations

import math

import numpy as np

from .statistics import background_adu


def _moments(img, yy, xx):
    w = np.clip(img, 0, None)
    t = float(w.sum())
    if t <= 0:
        return math.nan, math.nan, math.nan
    cx, cy = float((w * xx).sum() / t), float((w * yy).sum() / t)
    s2 = float((w * ((xx - cx) ** 2 + (yy - cy) ** 2)).sum() / t) / 2
    return cx, cy, math.sqrt(max(s2, 0.0))


def star_table(res, truth, radius_px: float = 4.0, max_rows: int = 500, usable=None) -> list[dict]:
    """Rows of the per-star table (see the module docstring); ``usable``: the pixels compared (else all finite)."""
    if truth is None or len(truth) == 0 or "kind" not in truth.dtype.names:
        return []
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    st = truth[np.isin(kind, ("star", "synthetic"))]  # catalogue stars and the model's faint population
    h, w = res.data_adu.shape
    rad = math.ceil(radius_px)
    inside = (st["x"] > rad) & (st["x"] < w - 1 - rad) & (st["y"] > rad) & (st["y"] < h - 1 - rad)
    st = st[inside]
    st = st[np.argsort(-st["flux_e"])][:max_rows]
    yy, xx = np.mgrid[-rad:rad + 1, -rad:rad + 1]
    ap = (xx ** 2 + yy ** 2) <= radius_px ** 2
    bg = background_adu(res)
    ok_px = np.isfinite(res.data_adu) if usable is None else usable
    rows = []
    for s in st:
        x, y = float(s["x"]), float(s["y"])
        xi, yi = round(x), round(y)
        sl = (slice(yi - rad, yi + rad + 1), slice(xi - rad, xi + rad + 1))
        d = (res.data_adu[sl] - bg[sl]) * ap
        m = (res.model_adu[sl] - bg[sl]) * ap
        var = float((res.var_adu2[sl] * ap).sum())
        fd, fm = float(d.sum()), float(m.sum())
        row = {"x": round(x, 3), "y": round(y, 3),
               "mag": round(float(s["mag"]), 4) if "mag" in st.dtype.names and np.isfinite(s["mag"]) else None,
               "flux_catalogue_adu": round(fm, 3), "flux_measured_adu": round(fd, 3)}
        if not ok_px[sl][ap].all():
            row["flag"] = "masked, saturated or outlier pixel in the aperture"
        elif fm > 0:
            cxd, cyd, sd = _moments(d, yy, xx)
            cxm, cym, sm = _moments(m, yy, xx)
            row.update(ratio=round(fd / fm, 5), ratio_err=round(math.sqrt(var) / fm, 5),
                       dx_px=round(cxd - cxm, 3), dy_px=round(cyd - cym, 3), size_measured_px=round(sd, 3),
                       size_catalogue_px=round(sm, 3))
        rows.append(row)
    return rows
