"""Score detections against labels: optimal one-to-one matching, completeness, purity, errors, PR curve.

Matching (per image): the cost of a (label, detection) pair is

- ``endpoints``: the mean distance of the two ends, with the ends' order free:
  min((|a0 - b0| + |a1 - b1|) / 2, (|a0 - b1| + |a1 - b0|) / 2) [px]; gate ``gate_px`` (default 3 px);
- ``centre``: the centre distance [px]; gate ``gate_px``;
- ``mask``: 1 - IoU of the masks; gate IoU >= ``min_iou`` (default 0.5).

Pairs beyond the gate cost a constant larger than any sum of gated costs, so
``scipy.optimize.linear_sum_assignment`` (Kuhn-Munkres; Crouse 2016, IEEE TAES 52, 1679) first maximises the
number of gated matches and then minimises their total cost; a greedy nearest-first match can lose a match
that the optimal one keeps (tests/scenes/test_bench_score.py). A label is detected when matched; a detection
is true when matched, a false alarm otherwise.

Metrics: completeness = matched labels / labels and purity = true detections / detections, overall and in
bins of the labels' SNR, angular rate, magnitude and length (purity in a bin counts the detections whose own
value falls in it: their matched label's, or for a false alarm the detection's own column when given, e.g.
the length of its endpoints), each with its Wilson score interval (Wilson 1927, JASA 22, 209; 68 %); the SNR
of 50 % completeness from a maximum-likelihood logistic fit p(SNR) = 1 / (1 + exp(-(SNR - SNR50) / w))
(Newton / IRLS, :func:`logistic_fit`) with a bootstrap error (labels resampled with replacement); endpoint and centre RMSE of the matches; false alarms
per megapixel and per frame; the precision-recall curve over the detection score and its average precision
(the area under the monotone precision envelope, all points, as in COCO/VOC 2010+).
"""

from __future__ import annotations

import base64
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

MATCH_MODES = ("endpoints", "mask", "centre")
GATE_PX = 3.0
MIN_IOU = 0.5
BIN_KEYS = {"snr": "snr", "rate": "rate_arcsec_s", "magnitude": "mag", "length": "length_px"}
WILSON_Z = 1.0  # 68 % intervals
N_BOOT = 200


class ScoreError(ValueError):
    """A detections or labels file that cannot be read: names the file and what was expected."""


@dataclass
class Item:
    """A label or a detection: image, endpoints, centre, optional mask (bbox-local) and properties."""

    image: str
    x0: float
    y0: float
    x1: float
    y1: float
    score: float = 1.0
    mask: np.ndarray | None = None
    mask_xy: tuple[int, int] = (0, 0)
    props: dict = field(default_factory=dict)

    @property
    def centre(self) -> tuple[float, float]:
        if "x" in self.props and "y" in self.props and self.props["x"] is not None:
            return float(self.props["x"]), float(self.props["y"])
        return 0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1)


# ------------------------------------------------------------------------------------------------ costs
def endpoint_cost(a: Item, b: Item) -> tuple[float, bool]:
    """Mean end distance with the order free; (cost, swapped)."""
    d_same = 0.5 * (math.hypot(a.x0 - b.x0, a.y0 - b.y0) + math.hypot(a.x1 - b.x1, a.y1 - b.y1))
    d_swap = 0.5 * (math.hypot(a.x0 - b.x1, a.y0 - b.y1) + math.hypot(a.x1 - b.x0, a.y1 - b.y0))
    return (d_swap, True) if d_swap < d_same else (d_same, False)


def centre_cost(a: Item, b: Item) -> float:
    (ax, ay), (bx, by) = a.centre, b.centre
    return math.hypot(ax - bx, ay - by)


def iou(a: Item, b: Item) -> float:
    if a.mask is None or b.mask is None:
        return 0.0
    (ax, ay), (bx, by) = a.mask_xy, b.mask_xy
    ah, aw = a.mask.shape
    bh, bw = b.mask.shape
    x0, y0, x1, y1 = max(ax, bx), max(ay, by), min(ax + aw, bx + bw), min(ay + ah, by + bh)
    inter = 0
    if x1 > x0 and y1 > y0:
        inter = int(np.sum(a.mask[y0 - ay:y1 - ay, x0 - ax:x1 - ax] & b.mask[y0 - by:y1 - by, x0 - bx:x1 - bx]))
    union = int(a.mask.sum()) + int(b.mask.sum()) - inter
    return inter / union if union else 0.0


def match(labels: list[Item], dets: list[Item], mode: str = "endpoints", gate_px: float = GATE_PX,
          min_iou: float = MIN_IOU) -> list[tuple[int, int, float]]:
    """Optimal one-to-one matches (label index, detection index, cost) within the gate (see the module notes)."""
    if not labels or not dets:
        return []
    n, m = len(labels), len(dets)
    if mode == "endpoints":
        a0, a1 = (np.array([[it.x0, it.y0] for it in labels])[:, None], np.array([[it.x1, it.y1] for it in labels])[:, None])
        b0, b1 = (np.array([[it.x0, it.y0] for it in dets])[None], np.array([[it.x1, it.y1] for it in dets])[None])
        d = lambda p, q: np.hypot(*(p - q).transpose(2, 0, 1))  # noqa: E731
        cost = np.minimum(d(a0, b0) + d(a1, b1), d(a0, b1) + d(a1, b0)) / 2
    elif mode == "centre":
        ca, cb = np.array([it.centre for it in labels]), np.array([it.centre for it in dets])
        cost = np.hypot(ca[:, None, 0] - cb[None, :, 0], ca[:, None, 1] - cb[None, :, 1])
    else:
        cost = np.array([[1.0 - iou(a, b) for b in dets] for a in labels])
    gate = gate_px if mode != "mask" else 1.0 - min_iou
    ok = cost <= gate
    big = (gate + 1.0) * (min(n, m) + 1)  # more than any sum of gated costs: matches first, then cost
    rows, cols = linear_sum_assignment(np.where(ok, cost, big))
    return [(int(i), int(j), float(cost[i, j])) for i, j in zip(rows, cols) if ok[i, j]]


def greedy_match(labels: list[Item], dets: list[Item], gate_px: float = GATE_PX) -> list[tuple[int, int, float]]:
    """Nearest-first centre matching (what the optimal match is compared with in the tests)."""
    pairs = sorted((centre_cost(a, b), i, j) for i, a in enumerate(labels) for j, b in enumerate(dets))
    used_i, used_j, out = set(), set(), []
    for c, i, j in pairs:
        if c <= gate_px and i not in used_i and j not in used_j:
            used_i.add(i)
            used_j.add(j)
            out.append((i, j, c))
    return out


# ---------------------------------------------------------------------------------------------- statistics
def wilson(k: int, n: int, z: float = WILSON_Z) -> tuple[float, float]:
    """Wilson score interval of a proportion k / n (Wilson 1927)."""
    if n == 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def logistic_fit(snr: np.ndarray, hit: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood (SNR50, width) of p = 1 / (1 + exp(-(snr - SNR50) / w)); NaN when undetermined.

    Newton's method (iteratively reweighted least squares; McCullagh & Nelder 1989, sec. 4.4) on the linear
    predictor ``a + b u`` with ``u = (snr - mean) / std``: gradient ``X^T (y - p)``, Hessian ``X^T W X``
    with ``W = p (1 - p)``, the step halved while the log-likelihood does not increase (it is concave, so
    this converges to the unique maximum). SNR50 = mean - a std / b, w = std / b. Undetermined (NaN): fewer
    than 3 finite SNRs, all or none detected, or b <= 0 (completeness not rising with SNR). Completely
    separated data (every miss below every hit) have no finite maximum (w -> 0): SNR50 is then the middle
    of the gap and w = 0.
    """
    snr, hit = np.asarray(snr, float), np.asarray(hit, bool)
    ok = np.isfinite(snr)
    snr, hit = snr[ok], hit[ok]
    if snr.size < 3 or hit.all() or not hit.any():
        return math.nan, math.nan
    lo_hit, hi_miss = float(snr[hit].min()), float(snr[~hit].max())
    if hi_miss < lo_hit:
        return 0.5 * (hi_miss + lo_hit), 0.0
    m, sd = float(snr.mean()), float(snr.std())
    if not sd > 0:
        return math.nan, math.nan
    u = (snr - m) / sd
    y = hit.astype(float)

    def loglik(a, b):
        z = a + b * u
        return -float(np.sum(np.logaddexp(0.0, np.where(hit, -z, z))))

    a, b = math.log(y.mean() / (1 - y.mean())), 0.0
    ll = loglik(a, b)
    for _ in range(100):
        p = 0.5 * (1.0 + np.tanh(0.5 * (a + b * u)))  # the logistic function without overflow
        r, w = y - p, p * (1.0 - p)
        g0, g1 = float(r.sum()), float(r @ u)
        wu = w * u
        h00, h01, h11 = float(w.sum()), float(wu.sum()), float(wu @ u)
        det = h00 * h11 - h01 * h01  # the 2 x 2 Newton system solved in closed form
        if not det > 0:
            return math.nan, math.nan
        da, db = (h11 * g0 - h01 * g1) / det, (h00 * g1 - h01 * g0) / det
        t = 1.0
        while t > 1e-6:
            ll_new = loglik(a + t * da, b + t * db)
            if ll_new >= ll - 1e-12 * abs(ll):
                break
            t *= 0.5
        a, b, ll = a + t * da, b + t * db, ll_new
        if abs(t * da) + abs(t * db) < 1e-10 * (1.0 + abs(a) + abs(b)):
            break
    if not b > 0:
        return math.nan, math.nan
    return m - a * sd / b, sd / b


def average_precision(scores: np.ndarray, tp: np.ndarray, n_truth: int) -> tuple[float, np.ndarray, np.ndarray]:
    """(AP, recall, precision) over the detections sorted by score (all-points envelope)."""
    if n_truth == 0 or scores.size == 0:
        return (math.nan if n_truth == 0 else 0.0), np.zeros(0), np.zeros(0)
    order = np.argsort(-scores, kind="stable")
    ctp = np.cumsum(tp[order])
    prec = ctp / np.arange(1, scores.size + 1)
    rec = ctp / n_truth
    env = np.maximum.accumulate(prec[::-1])[::-1]
    r = np.r_[0.0, rec]
    return float(np.sum((r[1:] - r[:-1]) * env)), rec, prec


def _edges(values: np.ndarray, key: str, nbins: int) -> np.ndarray:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return np.zeros(0)
    if key == "snr" and v.min() > 0:
        return np.unique(np.geomspace(v.min(), v.max() * (1 + 1e-9), nbins + 1))
    return np.unique(np.linspace(v.min(), v.max() + 1e-9 * max(1.0, abs(v.max())), nbins + 1))


# ------------------------------------------------------------------------------------------------ scoring
def score(labels: list[Item], dets: list[Item], *, mode: str = "endpoints", gate_px: float = GATE_PX,
          min_iou: float = MIN_IOU, images: dict | None = None, nbins: int = 8, seed: int = 0) -> dict:
    """Every metric of the module notes as a JSON-ready dict. ``images``: image -> (rows, cols) (false
    alarms per megapixel; default: the images of the labels, of unknown size -> NaN)."""
    if mode not in MATCH_MODES:
        raise ScoreError(f"unknown match mode {mode!r}: expected one of {', '.join(MATCH_MODES)}")
    names = sorted({it.image for it in labels} | {it.image for it in dets} | set(images or {}))
    hit = np.zeros(len(labels), bool)
    tp = np.zeros(len(dets), bool)
    match_of_det = np.full(len(dets), -1)
    end_err, cen_err = [], []
    by_l = {n: [] for n in names}
    by_d = {n: [] for n in names}
    for i, it in enumerate(labels):
        by_l[it.image].append(i)
    for j, it in enumerate(dets):
        by_d[it.image].append(j)
    for n in names:
        li, dj = by_l[n], by_d[n]
        for a, b, _ in match([labels[i] for i in li], [dets[j] for j in dj], mode, gate_px, min_iou):
            i, j = li[a], dj[b]
            hit[i], tp[j], match_of_det[j] = True, True, i
            c, _ = endpoint_cost(labels[i], dets[j])
            end_err.append(c)
            cen_err.append(centre_cost(labels[i], dets[j]))
    n_l, n_d = len(labels), len(dets)
    k_l, k_d = int(hit.sum()), int(tp.sum())
    fa = n_d - k_d
    npix = sum(int(np.prod(images[n])) for n in names if images and n in images)
    out = {"match": mode, "gate": {"px": gate_px} if mode != "mask" else {"min_iou": min_iou},
           "frames": len(names), "labels": n_l, "detections": n_d, "matched": k_l,
           "completeness": k_l / n_l if n_l else None, "completeness_interval": list(wilson(k_l, n_l)),
           "purity": k_d / n_d if n_d else None, "purity_interval": list(wilson(k_d, n_d)),
           "false_alarms": fa, "false_alarms_per_frame": fa / len(names) if names else None,
           "false_alarms_per_megapixel": fa / (npix / 1e6) if npix else None,
           "endpoint_rmse_px": float(np.sqrt(np.mean(np.square(end_err)))) if end_err else None,
           "centre_rmse_px": float(np.sqrt(np.mean(np.square(cen_err)))) if cen_err else None,
           "wilson_z": WILSON_Z}
    bins = {}
    for name, key in BIN_KEYS.items():
        lv = np.array([_prop(it, key) for it in labels], float)
        dv = np.array([_prop(labels[match_of_det[j]], key) if tp[j] else _det_prop(dets[j], key) for j in range(n_d)],
                      float)
        edges = _edges(lv, name, nbins)
        rows = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            inl = (lv >= lo) & (lv < hi)
            ind = (dv >= lo) & (dv < hi)
            nl, kl, nd, kd = int(inl.sum()), int(hit[inl].sum()), int(ind.sum()), int(tp[ind].sum())
            rows.append({"lo": float(lo), "hi": float(hi), "labels": nl, "matched": kl,
                         "completeness": kl / nl if nl else None, "completeness_interval": list(wilson(kl, nl)),
                         "detections": nd, "true": kd, "purity": kd / nd if nd else None,
                         "purity_interval": list(wilson(kd, nd))})
        bins[name] = rows
    out["bins"] = bins
    snr = np.array([_prop(it, "snr") for it in labels], float)
    s50, width = logistic_fit(snr, hit)
    boot = []
    if np.isfinite(s50):
        rng = np.random.default_rng(seed)
        for _ in range(N_BOOT):
            k = rng.integers(0, n_l, n_l)
            b, _w = logistic_fit(snr[k], hit[k])
            if np.isfinite(b):
                boot.append(b)
    out["snr50"] = {"value": _f(s50), "width": _f(width), "bootstrap_error": _f(np.std(boot, ddof=1)) if len(boot) > 2
                    else None, "bootstrap_samples": len(boot)}
    scores = np.array([d.score for d in dets], float)
    ap, rec, prec = average_precision(scores, tp, n_l)
    out["average_precision"] = _f(ap)
    out["figures"] = {
        "completeness_vs_snr": {"snr_lo": [r["lo"] for r in bins["snr"]], "snr_hi": [r["hi"] for r in bins["snr"]],
                                "completeness": [r["completeness"] for r in bins["snr"]],
                                "interval": [r["completeness_interval"] for r in bins["snr"]],
                                "logistic": {"snr50": _f(s50), "width": _f(width)}},
        "precision_recall": {"recall": rec.tolist(), "precision": prec.tolist(),
                             "score": np.sort(scores)[::-1].tolist()},
    }
    return _clean(out)


def _prop(it: Item, key: str) -> float:
    v = it.props.get(key)
    return math.nan if v is None else float(v)


def _det_prop(d: Item, key: str) -> float:
    if key == "length_px" and "length_px" not in d.props:
        return math.hypot(d.x1 - d.x0, d.y1 - d.y0)
    return _prop(d, key)


def _f(v):
    return None if v is None or not math.isfinite(float(v)) else float(v)


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (float, np.floating)):
        return _f(o)
    if isinstance(o, np.integer):
        return int(o)
    return o


# ------------------------------------------------------------------------------------------------ reading
def _rle_mask(seg, bbox) -> tuple[np.ndarray, tuple[int, int]]:
    from pycocotools import mask as cmask

    m = cmask.decode(seg if isinstance(seg["counts"], bytes) else {"size": seg["size"],
                                                                     "counts": seg["counts"].encode()}).astype(bool)
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if rows.size == 0:
        return np.zeros((1, 1), bool), (int(bbox[0]), int(bbox[1]))
    return m[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1], (int(cols[0]), int(rows[0]))


def _coco_item(a: dict, image: str, with_mask: bool) -> Item:
    x, y, w, h = a.get("bbox", [math.nan] * 4)
    if all(k in a and a[k] is not None for k in ("x0", "y0", "x1", "y1")):
        x0, y0, x1, y1 = (float(a[k]) for k in ("x0", "y0", "x1", "y1"))
    else:  # a plain box: its centre, no length (pixel-edge bbox -> centre convention)
        cx, cy = x + w / 2 - 0.5, y + h / 2 - 0.5
        x0 = x1 = cx
        y0 = y1 = cy
    mask, xy = (None, (0, 0))
    if with_mask and isinstance(a.get("segmentation"), dict):
        mask, xy = _rle_mask(a["segmentation"], a.get("bbox", [0, 0, 0, 0]))
    return Item(image, x0, y0, x1, y1, float(a.get("score", 1.0)), mask, xy,
                {k: v for k, v in a.items() if k not in ("segmentation",)})


def load_labels(path, kinds=("object",), with_mask: bool = False) -> tuple[list[Item], dict]:
    """Labels from a COCO file written by ``--labels coco`` (or a dataset's), or from a label FITS (a frame
    with ``TRUTH`` and ``LABELS``: :func:`load_labels_fits`); only ``kinds`` (default the objects; ``None``:
    all). Returns (items, image -> (rows, cols))."""
    path = Path(path)
    if path.suffix.lower() in (".fits", ".fit", ".fts") or path.name.lower().endswith((".fits.gz", ".fits.fz")):
        return load_labels_fits(path, kinds, with_mask)
    try:
        doc = json.loads(path.read_text())
        imgs = {im["id"]: im for im in doc["images"]}
        anns = doc["annotations"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ScoreError(f"{path}: not a COCO labels file ({exc}); expected the .coco.json of --labels coco") from None
    items = [_coco_item(a, imgs[a["image_id"]]["file_name"], with_mask) for a in anns
             if kinds is None or a.get("kind", "object") in kinds]
    return items, {im["file_name"]: (im["height"], im["width"]) for im in imgs.values()}


def load_labels_fits(path, kinds=("object",), with_mask: bool = False) -> tuple[list[Item], dict]:
    """Labels from a frame written with ``--labels fits``: its ``TRUTH`` table, its ``LABELS`` image (the
    TRUTH row of each pixel's dominant source) and, when present, its ``LABELCAT`` table (every label field).

    With ``LABELCAT`` the labels are exactly those of the COCO file (SNR, rate, length, ...); the mask of a
    label is the pixels of the ``LABELS`` image holding its row (where two masks overlap, the pixel goes to
    the dominant source only: mask IoUs of overlapping sources differ slightly from the COCO masks). Without
    it (a ``LABELS`` image written by other code), the labels are the TRUTH rows with pixels in the image
    or a centre on the frame, with TRUTH's endpoints, centre, magnitude and times; SNR and angular rate
    unknown (no SNR bins, no SNR50), the length from the endpoints. The image is named by the file's name.
    """
    from astropy.io import fits
    from scipy import ndimage

    path = Path(path)
    try:
        with fits.open(path) as h:
            names = [x.name for x in h]
            missing = [e for e in ("TRUTH", "LABELS") if e not in names]
            if missing:
                raise ScoreError(f"{path}: no {' and no '.join(missing)} extension; expected a frame written with "
                                 "--labels fits (TRUTH + LABELS) or the .coco.json of --labels coco")
            img = np.asarray(h["LABELS"].data)
            truth = np.asarray(h["TRUTH"].data)
            cat = np.asarray(h["LABELCAT"].data) if "LABELCAT" in names else None
    except ScoreError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ScoreError(f"{path}: cannot read the label FITS ({exc}); expected a frame written with "
                         "--labels fits") from None
    if img.ndim != 2:
        raise ScoreError(f"{path}: LABELS is not a 2-D image; expected the integer image of --labels fits")
    shape = tuple(int(n) for n in img.shape)
    image = path.name
    slices = ndimage.find_objects(img.astype(np.int64) + 1)  # value r -> slices[r] (NO_SOURCE = -1 -> background)

    def mask_of(r: int):
        sl = slices[r] if 0 <= r < len(slices) else None
        if sl is None:
            return None, (0, 0)
        return img[sl] == r, (sl[1].start, sl[0].start)

    def text(v):
        return v.decode().strip() if isinstance(v, bytes) else str(v).strip()

    items = []
    if cat is not None:
        for rec in cat:
            props = {k: (text(rec[k]) if k in ("kind", "name") else
                         (bool(rec[k]) if k == "edge" else
                          (int(rec[k]) if k in ("row", "source_id", "mask_pixels") else float(rec[k]))))
                     for k in cat.dtype.names if not k.startswith("bbox_")}
            props = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in props.items()}
            if kinds is not None and props.get("kind", "object") not in kinds:
                continue
            props["bbox"] = [int(rec[k]) for k in ("bbox_x", "bbox_y", "bbox_w", "bbox_h")]
            m, xy = mask_of(int(rec["row"])) if with_mask else (None, (0, 0))
            items.append(Item(image, float(rec["x0"]), float(rec["y0"]), float(rec["x1"]), float(rec["y1"]), 1.0,
                              m, xy, props))
        return items, {image: shape}
    for r, t in enumerate(truth):
        kind = text(t["kind"])
        if kinds is not None and kind not in kinds:
            continue
        sl = slices[r] if r < len(slices) else None
        x, y = float(t["x"]), float(t["y"])
        on = np.isfinite(x) and np.isfinite(y) and -0.5 <= x < shape[1] - 0.5 and -0.5 <= y < shape[0] - 0.5
        if sl is None and not on:
            continue
        x0, y0, x1, y1 = (float(t[k]) for k in ("x0", "y0", "x1", "y1"))
        if not all(np.isfinite(v) for v in (x0, y0, x1, y1)):
            x0 = x1 = x
            y0 = y1 = y
        props = {"row": r, "kind": kind, "name": text(t["name"]), "x": x, "y": y, "mag": _f(t["mag"]),
                 "t0_s": _f(t["t0_s"]), "t1_s": _f(t["t1_s"]), "length_px": math.hypot(x1 - x0, y1 - y0),
                 "snr": None, "rate_arcsec_s": None}
        m, xy = mask_of(r) if with_mask else (None, (0, 0))
        items.append(Item(image, x0, y0, x1, y1, 1.0, m, xy, props))
    return items, {image: shape}


def load_detections(path, label_images: dict, with_mask: bool = False) -> list[Item]:
    """Detections from a COCO results JSON (list of {image_id, bbox, score, [segmentation], [x0, y0, x1,
    y1]}), a CSV/ECSV table (columns x0, y0, x1, y1 or x, y; score; image or file_name when there are
    several images) or a mask FITS (an integer image: 0 background, k > 0 detection k; or boolean; score
    from a SCORES table when present). ``label_images``: the labels' image names (image ids are resolved
    in the labels' order, 1-based as in the COCO file)."""
    path = Path(path)
    names = list(label_images)
    one = names[0] if len(names) == 1 else None
    suf = path.suffix.lower()
    try:
        if suf == ".json":
            doc = json.loads(path.read_text())
            if isinstance(doc, dict):
                doc = doc.get("annotations", [])
            out = []
            for a in doc:
                im = a.get("file_name") or (names[int(a["image_id"]) - 1] if "image_id" in a else one)
                out.append(_coco_item(a, im, with_mask))
            return out
        if suf in (".csv", ".ecsv"):
            from astropy.table import Table

            t = Table.read(path, format="ascii.ecsv" if suf == ".ecsv" else "ascii.csv")
            cols = set(t.colnames)
            out = []
            for r in t:
                im = str(r["image"]) if "image" in cols else (str(r["file_name"]) if "file_name" in cols else one)
                if {"x0", "y0", "x1", "y1"} <= cols:
                    x0, y0, x1, y1 = (float(r[k]) for k in ("x0", "y0", "x1", "y1"))
                elif {"x", "y"} <= cols:
                    x0 = x1 = float(r["x"])
                    y0 = y1 = float(r["y"])
                else:
                    raise ScoreError(f"{path}: columns x0, y0, x1, y1 (or x, y) expected, found {sorted(cols)}")
                props = {k: float(r[k]) for k in cols if k in ("snr", "mag", "rate_arcsec_s", "length_px", "x", "y")}
                out.append(Item(im, x0, y0, x1, y1, float(r["score"]) if "score" in cols else 1.0, None, (0, 0), props))
            return out
        if suf in (".fits", ".fit", ".fts"):
            return _mask_fits(path, one)
    except ScoreError:
        raise
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise ScoreError(f"{path}: cannot read detections ({exc})") from None
    raise ScoreError(f"{path}: unknown detections format; expected .json (COCO results), .csv/.ecsv or .fits (mask)")


def _mask_fits(path: Path, image: str | None) -> list[Item]:
    from astropy.io import fits
    from scipy import ndimage

    with fits.open(path) as h:
        hdu = next((x for x in h if x.data is not None and getattr(x, "is_image", False) and x.data.ndim == 2), None)
        if hdu is None:
            raise ScoreError(f"{path}: no 2-D mask image")
        lab = np.asarray(hdu.data)
        scores = {int(r["id"]): float(r["score"]) for r in h["SCORES"].data} if "SCORES" in h else {}
    if lab.dtype == bool or lab.max() <= 1:
        lab, _ = ndimage.label(lab > 0)
    out = []
    for k, sl in enumerate(ndimage.find_objects(lab.astype(np.int64)), start=1):
        if sl is None:
            continue
        m = lab[sl] == k
        yy, xx = np.nonzero(m)
        yy, xx = yy + sl[0].start, xx + sl[1].start
        cx, cy = float(xx.mean()), float(yy.mean())
        # ends: the extreme mask pixels along the principal axis
        c = np.cov(np.vstack([xx, yy])) if xx.size > 1 else np.eye(2)
        ev, evec = np.linalg.eigh(np.atleast_2d(c))
        u = evec[:, -1]
        t = (xx - cx) * u[0] + (yy - cy) * u[1]
        p0, p1 = (cx + t.min() * u[0], cy + t.min() * u[1]), (cx + t.max() * u[0], cy + t.max() * u[1])
        out.append(Item(image, p0[0], p0[1], p1[0], p1[1], scores.get(k, float(m.sum())), m,
                        (sl[1].start, sl[0].start), {"x": cx, "y": cy}))
    return out


def score_files(detections, labels, mode: str = "endpoints", gate_px: float = GATE_PX, min_iou: float = MIN_IOU,
                kinds=("object",)) -> dict:
    """:func:`score` of a detections file against a labels file."""
    labs, images = load_labels(labels, kinds, with_mask=mode == "mask")
    dets = load_detections(detections, images, with_mask=mode == "mask")
    unknown = sorted({d.image for d in dets} - set(images))
    if unknown:
        raise ScoreError(f"{detections}: detections on images not in the labels ({unknown[0]!r}, ...)")
    out = score(labs, dets, mode=mode, gate_px=gate_px, min_iou=min_iou, images=images)
    out.update({"detections_file": str(detections), "labels_file": str(labels), "kinds": list(kinds or ["all"])})
    return out


# ------------------------------------------------------------------------------------------------ report
def figures_png(result: dict) -> dict[str, bytes]:
    """The report's plots (completeness vs SNR with the logistic fit; PR curve) as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    c = result["figures"]["completeness_vs_snr"]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    lo, hi = np.array(c["snr_lo"], float), np.array(c["snr_hi"], float)
    mid = np.sqrt(lo * hi) if lo.size and np.all(lo > 0) else 0.5 * (lo + hi)
    comp = np.array([np.nan if v is None else v for v in c["completeness"]], float)
    ci = np.array([[np.nan if v is None else v for v in iv] for iv in c["interval"]], float).reshape(-1, 2)
    if mid.size:
        # a bin at 0 or 100 % has its point on the interval's edge: rounding can make that length -1e-17
        yerr = np.clip(np.nan_to_num([comp - ci[:, 0], ci[:, 1] - comp]), 0.0, None)
        ax.errorbar(mid, comp, yerr=yerr, fmt="o", label="completeness (Wilson 68 %)")
        lg = c["logistic"]
        if lg["snr50"] is not None:
            s = np.geomspace(max(lo.min(), 1e-3), hi.max(), 200)
            ax.plot(s, 1 / (1 + np.exp(-(s - lg["snr50"]) / lg["width"])), "-", label=f"logistic, SNR50 = {lg['snr50']:.2f}")
        ax.set_xscale("log" if np.all(lo > 0) else "linear")
    ax.set_xlabel("matched-filter SNR")
    ax.set_ylabel("completeness")
    ax.set_ylim(-0.05, 1.05)
    ax.legend(fontsize=8)
    out["completeness_vs_snr"] = _png(fig)
    pr = result["figures"]["precision_recall"]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(pr["recall"], pr["precision"], "-")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ap = result["average_precision"]
    ax.set_title(f"AP = {ap:.3f}" if ap is not None else "AP undefined")
    out["precision_recall"] = _png(fig)
    plt.close("all")
    return out


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def html_report(result: dict) -> str:
    """A self-contained HTML report: the summary, the binned tables and the plots (PNG in base64)."""
    pngs = figures_png(result)
    rows = "".join(f"<tr><td>{k}</td><td>{_fmt(result[k])}</td></tr>" for k in (
        "match", "frames", "labels", "detections", "matched", "completeness", "purity", "false_alarms",
        "false_alarms_per_frame", "false_alarms_per_megapixel", "endpoint_rmse_px", "centre_rmse_px",
        "average_precision"))
    s50 = result["snr50"]
    rows += f"<tr><td>SNR of 50 % completeness</td><td>{_fmt(s50['value'])} &plusmn; {_fmt(s50['bootstrap_error'])}</td></tr>"
    tables = ""
    for name, bins in result["bins"].items():
        body = "".join(f"<tr><td>{_fmt(b['lo'])} - {_fmt(b['hi'])}</td><td>{b['labels']}</td><td>{_fmt(b['completeness'])} "
                       f"[{_fmt(b['completeness_interval'][0])}, {_fmt(b['completeness_interval'][1])}]</td>"
                       f"<td>{b['detections']}</td><td>{_fmt(b['purity'])}</td></tr>" for b in bins)
        tables += (f"<h3>{name}</h3><table><tr><th>bin</th><th>labels</th><th>completeness [68 %]</th>"
                   f"<th>detections</th><th>purity</th></tr>{body}</table>")
    imgs = "".join(f'<h3>{k}</h3><img alt="{k}" src="data:image/png;base64,{base64.b64encode(v).decode()}">'
                   for k, v in pngs.items())
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>newtsim score</title><style>"
            "body{font-family:sans-serif} td,th{padding:2px 8px;border-bottom:1px solid #ddd}</style></head><body>"
            f"<h1>Detection score</h1><table>{rows}</table>{imgs}{tables}</body></html>")


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
