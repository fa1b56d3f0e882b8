"""Label files: COCO instances (RLE masks), SatNet-style JSON, YOLO oriented boxes, the FITS ``LABELS`` image.

Every format carries the label rule (:func:`scenes.app.bench.labels.label_rule`). Coordinates follow the
labels' convention (0-based pixel centres; ``bbox`` in whole pixels from the first column/row, which is
COCO's pixel-edge convention).

- **COCO** (``coco``): one file for a frame or a dataset: ``images`` (id, file_name, width, height, seed,
  split), ``categories`` (1 ``object``, 2 ``star``: catalogue and model stars), ``annotations`` with
  ``bbox``, ``area`` (mask pixels), ``iscrowd = 0``, ``segmentation`` as compressed RLE (pycocotools'
  column-major run lengths over the whole image, built from the bbox mask without a frame-sized array) and
  every label field (endpoints, times, RA/Dec, flux, SNR, rate, ...). Loads in ``pycocotools.coco.COCO``.
- **SatNet** (``satnet``): the per-image JSON that SatSim writes for the SatNet data sets, one entry per
  frame in a list: ``{"data": {"file": {"filename", "dirname"}, "sensor": {"height", "width", ...},
  "objects": [{"class_name", "class_id", "type", "x_min", "y_min", "x_max", "y_max", "x_center",
  "y_center", "x_start", "y_start", "x_end", "y_end", "magnitude", "snr", ...}]}}``; positions are
  fractions of the image width/height measured from the top-left corner (pixel edges), as in SatSim.
- **YOLO** (``yolo``): the oriented-box text format of Ultralytics (``class x1 y1 x2 y2 x3 y3 x4 y4``,
  normalised to the image). A streak's box is the rectangle along its path with corners ``p0 + h n,
  p1 + h n, p1 - h n, p0 - h n`` (n the unit normal, h the mask's half-width): the midpoints of the two
  short edges are exactly the endpoints (:func:`yolo_endpoints`). A point source: an axis-aligned square.
  Classes: 0 object, 1 star.
- **FITS** (``fits``): extension ``LABELS`` of the frame, an integer image holding the TRUTH row of each
  pixel's dominant source (:func:`scenes.app.bench.labels.dominant_source_image`), -1 elsewhere.
"""

from __future__ import annotations

import json
import math

import numpy as np
from astropy.io import fits

from .labels import NO_SOURCE, Label, dominant_source_image, label_rule

FORMATS = ("coco", "satnet", "yolo", "fits")
CATEGORIES = [{"id": 1, "name": "object", "supercategory": "source"},
              {"id": 2, "name": "star", "supercategory": "source"}]


def parse_formats(text: str | None) -> list[str]:
    """``"coco,fits"`` -> ["coco", "fits"]; ValueError naming the unknown one."""
    if not text:
        return []
    out = [f.strip().lower() for f in text.split(",") if f.strip()]
    bad = [f for f in out if f not in FORMATS]
    if bad:
        raise ValueError(f"unknown label format {bad[0]!r}: expected one or more of {', '.join(FORMATS)}")
    return list(dict.fromkeys(out))


def category_id(kind: str) -> int:
    return 2 if kind in ("star", "synthetic") else 1


# ------------------------------------------------------------------------------------------------ COCO
def rle_of(label: Label, shape: tuple[int, int]) -> dict:
    """Compressed COCO RLE of a label's mask on an image of ``shape`` (no frame-sized array)."""
    from pycocotools import mask as cmask

    h_img, w_img = shape
    x, y, w, h = label.bbox
    m = label.mask if label.mask_pixels else np.zeros((h, w), dtype=bool)
    cc, rr = np.nonzero(m.T)  # column-major order: column, then row
    idx = (x + cc).astype(np.int64) * h_img + (y + rr)
    if idx.size:
        brk = np.flatnonzero(idx[1:] - idx[:-1] != 1)
        n = brk.size + 1
        starts, ends = np.empty(n, dtype=np.int64), np.empty(n + 1, dtype=np.int64)
        starts[0], starts[1:] = idx[0], idx[brk + 1]
        ends[0], ends[1:-1], ends[-1] = 0, idx[brk] + 1, idx[-1] + 1  # ends[0]: the image start
        c = np.empty(2 * n + 1, dtype=np.int64)  # gap, run, gap, run, ..., the rest of the image
        c[0:-1:2] = starts - ends[:-1]
        c[1::2] = ends[1:] - starts
        c[-1] = h_img * w_img - ends[-1]
        counts = c.tolist()
    else:
        counts = [h_img * w_img]
    rle = cmask.frPyObjects({"size": [h_img, w_img], "counts": counts}, h_img, w_img)
    return {"size": [int(h_img), int(w_img)], "counts": rle["counts"].decode("ascii")}


def coco_annotation(label: Label, image_id: int, ann_id: int, shape) -> dict:
    rec = label.record()
    rec.update({"id": ann_id, "image_id": image_id, "category_id": category_id(label.kind),
                "bbox": [float(v) for v in label.bbox], "area": float(label.mask_pixels), "iscrowd": 0,
                "segmentation": rle_of(label, shape)})
    return rec


def coco_document(frames: list[dict], mask_fraction_sigma: float) -> dict:
    """A COCO instances document. ``frames``: dicts with ``file_name``, ``shape``, ``labels`` and any
    extra image keys (``seed``, ``split``, ``scene``)."""
    images, anns = [], []
    for i, fr in enumerate(frames, start=1):
        h, w = fr["shape"]
        img = {"id": i, "file_name": fr["file_name"], "width": int(w), "height": int(h)}
        img.update({k: v for k, v in fr.items() if k not in ("file_name", "shape", "labels")})
        images.append(img)
        for lab in fr["labels"]:
            anns.append(coco_annotation(lab, i, len(anns) + 1, (h, w)))
    return {"info": {"description": "newtsim labels", "label_rule": label_rule(mask_fraction_sigma)},
            "images": images, "annotations": anns, "categories": CATEGORIES}


# ---------------------------------------------------------------------------------------------- SatNet
def satnet_frame(labels: list[Label], shape, file_name: str, sensor: dict | None = None) -> dict:
    """One frame in SatSim's SatNet annotation layout (fractions of the image from the top-left edge)."""
    h, w = shape
    objs = []
    for lab in labels:
        x, y, bw, bh = lab.bbox
        objs.append({
            "class_name": "Satellite" if category_id(lab.kind) == 1 else "Star",
            "class_id": category_id(lab.kind),
            "type": "line" if lab.length_px > 0 else "point",
            "x_min": x / w, "y_min": y / h, "x_max": (x + bw) / w, "y_max": (y + bh) / h,
            "x_center": (lab.x + 0.5) / w, "y_center": (lab.y + 0.5) / h,
            "x_start": (lab.x0 + 0.5) / w, "y_start": (lab.y0 + 0.5) / h,
            "x_end": (lab.x1 + 0.5) / w, "y_end": (lab.y1 + 0.5) / h,
            "bbox_width": bw / w, "bbox_height": bh / h,
            "magnitude": _num(lab.mag), "snr": _num(lab.snr), "pe_per_sec": _num(lab.flux_e / max(lab.t1_s - lab.t0_s,
                                                                                                    1e-30)
                                                                               if lab.t1_s > lab.t0_s else math.nan),
            "source": "newtsim", "truth_row": lab.row, **{k: v for k, v in lab.record().items() if k not in ("bbox",)},
        })
    return {"data": {"file": {"filename": file_name, "dirname": ""},
                     "sensor": {"height": int(h), "width": int(w), **(sensor or {})},
                     "objects": objs}}


def _num(v):
    return None if v is None or not math.isfinite(float(v)) else float(v)


# ------------------------------------------------------------------------------------------------ YOLO
def half_width_px(label: Label) -> float:
    """Half-width of the mask across the label's axis [px] (at least half a pixel)."""
    if not label.mask_pixels:
        return 0.5
    x, y, w, h = label.bbox
    rr, cc = np.nonzero(label.mask)
    px, py = cc + x - label.x0, rr + y - label.y0
    d = np.array([label.x1 - label.x0, label.y1 - label.y0])
    n = float(np.hypot(*d))
    if n == 0:
        return float(max(np.abs(px).max(), np.abs(py).max()) + 0.5)
    ux, uy = d / n
    return float(np.abs(-uy * px + ux * py).max() + 0.5)


def yolo_corners(label: Label) -> np.ndarray:
    """(4, 2) corners [px, centres convention] of the oriented box (see the module notes)."""
    hw = half_width_px(label)
    p0, p1 = np.array([label.x0, label.y0]), np.array([label.x1, label.y1])
    d = p1 - p0
    n = float(np.hypot(*d))
    if n == 0:
        return np.array([p0 + [-hw, -hw], p0 + [hw, -hw], p0 + [hw, hw], p0 + [-hw, hw]])
    u = d / n
    nrm = np.array([-u[1], u[0]]) * hw
    return np.array([p0 + nrm, p1 + nrm, p1 - nrm, p0 - nrm])


def yolo_endpoints(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The endpoints back from an oriented box: the midpoints of edges 4-1 and 2-3."""
    c = np.asarray(corners, dtype=float).reshape(4, 2)
    return 0.5 * (c[0] + c[3]), 0.5 * (c[1] + c[2])


#: mask pixels per pass of :func:`half_widths_px` (arrays of ~1 MB: below the size where numpy asks the
#: kernel for huge pages, whose first touch was 5x slower on the 2-core test machine)
HALF_WIDTH_CHUNK_PIXELS = 1 << 17


def half_widths_px(labels: list[Label]) -> np.ndarray:
    """:func:`half_width_px` of every label, the same numbers, in a few passes over all their mask pixels."""
    hw = np.full(len(labels), 0.5)
    sel = [i for i, lab in enumerate(labels) if lab.mask_pixels]
    start = 0
    while start < len(sel):
        stop, n = start + 1, labels[sel[start]].mask_pixels
        while stop < len(sel) and n + labels[sel[stop]].mask_pixels <= HALF_WIDTH_CHUNK_PIXELS:
            n += labels[sel[stop]].mask_pixels
            stop += 1
        hw[sel[start:stop]] = _half_widths([labels[i] for i in sel[start:stop]])
        start = stop
    return hw


def _half_widths(labs: list[Label]) -> np.ndarray:
    nz = [np.nonzero(lab.mask) for lab in labs]
    cnt = np.array([r.size for r, _ in nz])
    rr, cc = np.concatenate([r for r, _ in nz]), np.concatenate([c for _, c in nz])
    bx, by = (np.array([lab.bbox[k] for lab in labs], dtype=np.int64) for k in (0, 1))
    x0, y0, x1, y1 = (np.array([getattr(lab, k) for lab in labs], dtype=float) for k in ("x0", "y0", "x1", "y1"))
    px = (cc + np.repeat(bx, cnt)) - np.repeat(x0, cnt)
    py = (rr + np.repeat(by, cnt)) - np.repeat(y0, cnt)
    dx, dy = x1 - x0, y1 - y0
    n = np.hypot(dx, dy)
    point = n == 0
    n[point] = 1.0
    ux, uy = np.repeat(dx / n, cnt), np.repeat(dy / n, cnt)
    across = np.where(np.repeat(point, cnt), np.maximum(np.abs(px), np.abs(py)), np.abs(-uy * px + ux * py))
    starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    return np.maximum.reduceat(across, starts) + 0.5


def yolo_corners_all(labels: list[Label]) -> np.ndarray:
    """(n, 4, 2) :func:`yolo_corners` of every label (the same numbers, computed together)."""
    hw = half_widths_px(labels)[:, None]
    p0 = np.array([[lab.x0, lab.y0] for lab in labels], dtype=float).reshape(-1, 2)
    p1 = np.array([[lab.x1, lab.y1] for lab in labels], dtype=float).reshape(-1, 2)
    d = p1 - p0
    n = np.hypot(d[:, 0], d[:, 1])
    point = n == 0
    n[point] = 1.0
    u = d / n[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1) * hw
    c = np.stack([p0 + nrm, p1 + nrm, p1 - nrm, p0 - nrm], axis=1)
    sq = np.stack([p0 + np.concatenate([-hw, -hw], axis=1), p0 + np.concatenate([hw, -hw], axis=1),
                   p0 + np.concatenate([hw, hw], axis=1), p0 + np.concatenate([-hw, hw], axis=1)], axis=1)
    c[point] = sq[point]
    return c


def yolo_lines(labels: list[Label], shape) -> str:
    """Ultralytics OBB lines: ``class x1 y1 ... x4 y4`` normalised (pixel-edge coordinates / size)."""
    if not labels:
        return ""
    h, w = shape
    c = ((yolo_corners_all(labels) + 0.5) / np.array([w, h], dtype=float)).reshape(-1, 8).tolist()
    line = "%d " + " ".join(["%.7f"] * 8)
    return "\n".join(line % (category_id(lab.kind) - 1, *v) for lab, v in zip(labels, c)) + "\n"


# ------------------------------------------------------------------------------------------------ FITS
def labels_hdu(sources, labels: list[Label], shape, mask_fraction_sigma: float) -> fits.ImageHDU:
    """The ``LABELS`` extension (tile-compressed integer image, lossless)."""
    img = dominant_source_image(sources, labels, shape)
    # tiles of 16 full rows: 1/16 of the per-tile work of astropy's default row tiles (3x faster, smaller)
    hdu = fits.CompImageHDU(img, name="LABELS", compression_type="RICE_1",
                            tile_shape=(min(16, img.shape[0]), img.shape[1]))
    hdu.header["NOSOURCE"] = (NO_SOURCE, "value of a pixel in no source's mask")
    hdu.header["MASKSIG"] = (mask_fraction_sigma, "mask: s > MASKSIG x local noise sigma")
    hdu.header["COMMENT"] = "TRUTH row of the pixel's dominant source (largest expected signal among the"
    hdu.header["COMMENT"] = "masks holding the pixel); see docs/detection_bench.md"
    return hdu


#: the label fields of the ``LABELCAT`` table (one row per label; ``bbox`` as four columns; no mask: the
#: ``LABELS`` image holds the dominant source of each pixel)
LABELCAT_COLUMNS = ("row", "kind", "name", "source_id", "x", "y", "x0", "y0", "x1", "y1", "t0_s", "t1_s", "ra_deg",
                    "dec_deg", "ra0_deg", "dec0_deg", "ra1_deg", "dec1_deg", "bbox_x", "bbox_y", "bbox_w", "bbox_h",
                    "mask_pixels", "mask_flux_fraction", "flux_e", "flux_truth_e", "snr", "snr_peak", "mag",
                    "length_px", "rate_px_s", "rate_arcsec_s", "edge")


def labels_table_hdu(labels: list[Label]) -> fits.BinTableHDU:
    """The ``LABELCAT`` extension: every label's fields (what the COCO annotations carry but the mask), so
    a frame with ``TRUTH``, ``LABELS`` and ``LABELCAT`` is a complete labels file (``newtsim score``)."""
    types = {"row": "i4", "source_id": "i8", "mask_pixels": "i8", "edge": "?", "kind": "S9", "name": "S32",
             "bbox_x": "i4", "bbox_y": "i4", "bbox_w": "i4", "bbox_h": "i4"}
    arr = np.zeros(len(labels), dtype=[(k, types.get(k, "f8")) for k in LABELCAT_COLUMNS])
    for k in LABELCAT_COLUMNS:
        if k.startswith("bbox_"):
            arr[k] = [int(lab.bbox["xywh".index(k[-1])]) for lab in labels]
        elif k in ("kind", "name"):
            arr[k] = [str(getattr(lab, k)).encode("ascii", "replace")[:int(types[k][1:])] for lab in labels]
        else:
            arr[k] = [getattr(lab, k) for lab in labels]
    hdu = fits.BinTableHDU(arr, name="LABELCAT")
    hdu.header["COMMENT"] = "one row per label (docs/detection_bench.md); row = the TRUTH row, the LABELS value"
    return hdu


def write_json(obj, path) -> None:
    """Write ``obj`` as ``json.dump(obj, f, indent=1, allow_nan=False, default=...)`` writes it, byte for byte
    (:func:`dumps_indent1`), in one write."""
    text = dumps_indent1(obj)
    with open(path, "w") as f:
        f.write(text)


_ESC = json.encoder.encode_basestring_ascii  # the standard encoder's string escaping (C)


def _float(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"Out of range float values are not JSON compliant: {v!r}")
    return float.__repr__(v)


def _key(k) -> str:
    """A dict key as the standard encoder turns it into a string."""
    if isinstance(k, str):
        return k
    if isinstance(k, float):
        return _float(k)
    if k is True or k is False or k is None:
        return {True: "true", False: "false", None: "null"}[k]
    if isinstance(k, int):
        return int.__repr__(k)
    raise TypeError(f"keys must be str, int, float, bool or None, not {type(k).__name__}")


_SCALARS = frozenset((str, int, float, bool, type(None)))


def dumps_indent1(obj) -> str:
    """``json.dumps(obj, indent=1, allow_nan=False, default=_default)``: the same text, ~3x faster.

    The standard library writes indented JSON with its pure-Python generator (its C encoder only writes
    without indentation): ~1.8 million chunks for the COCO and SatNet files of a full IMX411 frame. Here
    the containers are walked in Python as the standard encoder walks them (the same type order, string
    escaping, float and int representations, separators ``","`` and ``": "``, one space per level), and
    each run of consecutive plain scalars (str, int, float, bool, None) of a dict or list is written by
    the standard C encoder with the item separator ``",\\n"`` + the indentation of its level, which is
    exactly what the indented encoder writes between those items. tests/scenes/test_bench_labels.py
    compares the two.
    """
    parts: list[str] = []
    app = parts.append
    flat: dict[int, json.JSONEncoder] = {}

    def run_text(run, level: int) -> str:
        """The items of a flat dict or list as the indented encoder writes them at ``level`` (no brackets)."""
        e = flat.get(level)
        if e is None:
            e = flat[level] = json.JSONEncoder(separators=(",\n" + " " * (level + 1), ": "), allow_nan=False)
        return e.encode(run)[1:-1]

    def enc(o, level: int) -> None:
        t = type(o)
        if t is str:
            app(_ESC(o))
        elif t is float:
            app(_float(o))
        elif t is int:
            app(int.__repr__(o))
        elif o is None:
            app("null")
        elif o is True:
            app("true")
        elif o is False:
            app("false")
        elif isinstance(o, str):
            app(_ESC(o))
        elif isinstance(o, int):
            app(int.__repr__(o))
        elif isinstance(o, float):
            app(_float(o))
        elif isinstance(o, (list, tuple)):
            if not o:
                app("[]")
                return
            ind = "\n" + " " * (level + 1)
            sep = "[" + ind
            run = []
            for v in o:
                if type(v) in _SCALARS:
                    run.append(v)
                    continue
                if run:
                    app(sep)
                    app(run_text(run, level))
                    sep, run = "," + ind, []
                app(sep)
                sep = "," + ind
                enc(v, level + 1)
            if run:
                app(sep)
                app(run_text(run, level))
            app("\n" + " " * level + "]")
        elif isinstance(o, dict):
            if not o:
                app("{}")
                return
            ind = "\n" + " " * (level + 1)
            sep = "{" + ind
            run = {}
            for k, v in o.items():
                if type(k) is str and type(v) in _SCALARS:
                    run[k] = v
                    continue
                if run:
                    app(sep)
                    app(run_text(run, level))
                    sep, run = "," + ind, {}
                app(sep)
                sep = "," + ind
                app(_ESC(k if type(k) is str else _key(k)))
                app(": ")
                enc(v, level + 1)
            if run:
                app(sep)
                app(run_text(run, level))
            app("\n" + " " * level + "}")
        else:
            enc(_default(o), level)

    enc(obj, 0)
    return "".join(parts)


def _default(v):
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return _num(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON: {type(v)}")
