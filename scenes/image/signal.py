"""The expected-signal callable of the detector chain: background plus PSF-integrated source samples.

Every source becomes samples ``(x, y, e, t_lo, t_hi, w)``: a point of ``e`` electrons at ``(x, y)``
[unbinned pixels of the read-out window, 0-based, pixel centres at integers] standing for the light that
arrives between ``t_lo`` and ``t_hi`` [s from the exposure start], drawn with a stamp of half-width ``w``
[pixels]. A static star is one sample with ``t_lo = -inf``, ``t_hi = +inf`` (its light during the whole
window of every row). A moving source (a streak) is a chain of samples, one per time interval of the
path (spacing <= 0.25 pixel of motion), each carrying ``flux x dt``.

Pixel ``(c, r)`` receives (thesis eqs. 10, 51)

    S(c, r) = sum_k e_k f_k(r) P(c - x_k, r - y_k),

with ``P`` the pixel-integrated PSF and ``f_k(r)`` the fraction of the sample's interval that lies in row
r's exposure window ``[r tau, r tau + T]`` (1 for static samples and for a global shutter). A rolling
shutter therefore records each row of a streak during its own time window: a source moving along x at
v px/s is displaced by v tau per row (shear), one moving along y is stretched by 1 / (1 - v_y tau).

The callable is evaluated per row band on worker threads: it reads the precomputed, y-sorted sample arrays
(never writes them), selects the samples whose stamps reach the band (binary search on y), groups them by
stamp size and scatters the stamps with ``numpy.bincount`` over the bounding box of each chunk, in float64,
and returns the band in float32. The work per band is proportional to the samples that reach it.

Paths (:class:`Trails`) are cut into segments of consecutive samples of one source (at most 2 (2w + 1)
pixels of motion each). With a separable PSF, P = ey (x) ex, a segment's contribution to its bounding box
is one matrix product, S = EY^T diag(e f) EX, with EY (K, rows) and EX (K, cols) holding each sample's row
and column fractions (and the rolling-shutter weights f folded into EY): BLAS instead of K scattered
stamps. Without ``factors`` (a non-separable PSF) the segments are rendered as point samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .motion import window_overlap

CHUNK_ELEMENTS = 1 << 21  # stamp pixels per vectorised chunk (memory ~ 16 bytes each, a few x)
TRAIL_CHUNK_ELEMENTS = 1 << 19  # trail samples x box width per chunk (~4 MB matrices: cache-friendlier)
#: Trails.concat copies the samples as slices when its merge leaves at most this many pieces, else gathers them
CONCAT_PIECES_MAX = 64


@dataclass
class Samples:
    """Point samples of the sources, sorted by ``y`` (see the module notes). All arrays (n,)."""

    x: np.ndarray
    y: np.ndarray
    e: np.ndarray
    t_lo: np.ndarray
    t_hi: np.ndarray
    w: np.ndarray

    @classmethod
    def empty(cls) -> Samples:
        z = np.zeros(0)
        return cls(z, z, z, z, z, np.zeros(0, dtype=np.int64))

    @classmethod
    def concat(cls, parts: list[Samples]) -> Samples:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("x", "y", "e", "t_lo", "t_hi", "w")}
        order = np.argsort(cat["y"], kind="stable")
        return cls(**{k: v[order] for k, v in cat.items()})

    def __len__(self) -> int:
        return int(self.x.size)

    def take(self, keep) -> Samples:
        return Samples(self.x[keep], self.y[keep], self.e[keep], self.t_lo[keep], self.t_hi[keep], self.w[keep])


def deposit(acc: np.ndarray, row0: int, col0: int, s: Samples, idx: np.ndarray, w: int, psf,
            row_time_s: float, exptime_s: float) -> None:
    """Add the stamps of samples ``idx`` (all of half-width ``w``) to ``acc`` (rows row0.., cols col0..).

    Coordinates are those of the samples (read-out window, unbinned); pixels outside ``acc`` are dropped.
    """
    nrow, ncol = acc.shape
    off = np.arange(-w, w + 1)
    x, y = s.x[idx], s.y[idx]
    cols = np.rint(x).astype(np.int64)[:, None] + off  # (n, 2w+1)
    rows = np.rint(y).astype(np.int64)[:, None] + off
    frac = psf(x, y, cols - x[:, None], rows - y[:, None])  # (n, wy, wx)
    rw = s.e[idx][:, None] * ((rows >= row0) & (rows < row0 + nrow))
    timed = np.isfinite(s.t_lo[idx])
    if row_time_s > 0 and timed.any():
        f = window_overlap(s.t_lo[idx][:, None], s.t_hi[idx][:, None], rows, row_time_s, exptime_s)
        rw = np.where(timed[:, None], rw * f, rw)
    cw = (cols >= col0) & (cols < col0 + ncol)
    vals = frac * rw[:, :, None] * cw[:, None, :]
    r_lo = max(row0, int(rows[:, 0].min()))
    r_hi = min(row0 + nrow, int(rows[:, -1].max()) + 1)
    c_lo = max(col0, int(cols[:, 0].min()))
    c_hi = min(col0 + ncol, int(cols[:, -1].max()) + 1)
    if r_hi <= r_lo or c_hi <= c_lo:
        return
    bw = c_hi - c_lo
    ri = np.clip(rows, r_lo, r_hi - 1) - r_lo
    ci = np.clip(cols, c_lo, c_hi - 1) - c_lo
    flat = (ri[:, :, None] * bw + ci[:, None, :]).ravel()
    box = np.bincount(flat, weights=vals.ravel(), minlength=(r_hi - r_lo) * bw)
    acc[r_lo - row0:r_hi - row0, c_lo - col0:c_hi - col0] += box.reshape(r_hi - r_lo, bw)


def render_samples(s: Samples, psf, row0: int, row1: int, col0: int, col1: int, row_time_s: float = 0.0,
                   exptime_s: float = 0.0) -> np.ndarray:
    """Expected electrons [e-] (float64) of the samples in rows [row0, row1) x cols [col0, col1)."""
    acc = np.zeros((row1 - row0, col1 - col0))
    if not len(s):
        return acc
    wmax = int(s.w.max())
    lo = int(np.searchsorted(s.y, row0 - 0.5 - wmax - 1, side="left"))
    hi = int(np.searchsorted(s.y, row1 - 0.5 + wmax + 1, side="right"))
    if hi <= lo:
        return acc
    cand = np.arange(lo, hi)
    iy = np.rint(s.y[cand]).astype(np.int64)
    ix = np.rint(s.x[cand]).astype(np.int64)
    ww = s.w[cand]
    reach = (iy + ww >= row0) & (iy - ww < row1) & (ix + ww >= col0) & (ix - ww < col1) & (s.e[cand] > 0)
    cand, ww = cand[reach], ww[reach]
    for w in np.unique(ww):
        sel = cand[ww == w]
        step = max(1, CHUNK_ELEMENTS // (2 * int(w) + 1) ** 2)
        for k in range(0, sel.size, step):
            deposit(acc, row0, col0, s, sel[k:k + step], int(w), psf, row_time_s, exptime_s)
    return acc


@dataclass
class Trails:
    """Samples of moving sources grouped in segments (consecutive samples of one source).

    ``x, y, e, t_lo, t_hi`` (n,) are the samples in segment order; segment ``k`` holds samples
    ``start[k]:start[k + 1]`` with stamp half-width ``w[k]`` and the pixel bounding box
    ``ylo..yhi`` x ``xlo..xhi`` (inclusive, stamps included). Segments are sorted by ``ylo``.
    """

    x: np.ndarray
    y: np.ndarray
    e: np.ndarray
    t_lo: np.ndarray
    t_hi: np.ndarray
    start: np.ndarray
    w: np.ndarray
    ylo: np.ndarray
    yhi: np.ndarray
    xlo: np.ndarray
    xhi: np.ndarray

    @classmethod
    def empty(cls) -> Trails:
        z, zi = np.zeros(0), np.zeros(0, dtype=np.int64)
        return cls(z, z, z, z, z, np.zeros(1, dtype=np.int64), zi, zi, zi, zi, zi)

    @classmethod
    def from_samples(cls, x, y, e, t_lo, t_hi, w, key) -> Trails:
        """Group samples by ``key`` (source x segment number; stable: the input order is kept inside), segments
        in increasing ``ylo`` (stable in ``key``).

        When each key's samples are one contiguous run of the input (a star's samples in time order), the stable
        sort by key only reorders the runs: the segments are measured on the input as it is and the samples
        gathered once, in their final order (:meth:`_grouped`: the same arrays as the sort)."""
        x, y, e, t_lo, t_hi, w, key = (np.ravel(a) for a in (x, y, e, t_lo, t_hi, w, key))
        if x.size == 0:
            return cls.empty()
        run = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        run_key = key[run]
        order = np.argsort(run_key, kind="stable")
        if run.size > 1 and not np.all(run_key[order[1:]] != run_key[order[:-1]]):  # a key in two runs
            return cls._grouped(x, y, e, t_lo, t_hi, w, key)

        def pixel(a):  # rint is monotonic: the rounded extremes of a run are the extremes of its rounded values
            return np.rint(a).astype(np.int64)

        ws = w[run].astype(np.int64)
        ylo = pixel(np.minimum.reduceat(y, run)) - ws
        order = order[np.argsort(ylo[order], kind="stable")]  # by key, then stably by ylo (:meth:`sorted`)
        return cls._take_runs((x, y, e, t_lo, t_hi), np.r_[run, x.size].astype(np.int64), order, ws, ylo,
                              pixel(np.maximum.reduceat(y, run)) + ws, pixel(np.minimum.reduceat(x, run)) - ws,
                              pixel(np.maximum.reduceat(x, run)) + ws)

    @classmethod
    def _grouped(cls, x, y, e, t_lo, t_hi, w, key) -> Trails:
        """:meth:`from_samples` for any key order: a stable sort of the samples by key, then :meth:`sorted`."""
        order = np.argsort(key, kind="stable")
        x, y, e, t_lo, t_hi, w, key = (a[order] for a in (x, y, e, t_lo, t_hi, w, key))
        start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ix, iy = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        ws = w[start].astype(np.int64)
        seg = cls(x, y, e, t_lo, t_hi, np.r_[start, x.size].astype(np.int64), ws,
                  np.minimum.reduceat(iy, start) - ws, np.maximum.reduceat(iy, start) + ws,
                  np.minimum.reduceat(ix, start) - ws, np.maximum.reduceat(ix, start) + ws)
        return seg.sorted()

    @classmethod
    def _take_runs(cls, arrays, bounds, order, w, ylo, yhi, xlo, xhi) -> Trails:
        """Segments ``order`` (of runs ``bounds[k]:bounds[k + 1]`` of ``arrays``), their samples gathered once."""
        lens = np.diff(bounds)[order]
        start = np.r_[0, np.cumsum(lens)].astype(np.int64)
        if np.array_equal(order, np.arange(order.size)):
            cols = tuple(np.array(a) for a in arrays)  # copies: the trails never share the caller's arrays
        else:
            idx = np.arange(int(start[-1])) + np.repeat(bounds[:-1][order] - start[:-1], lens)
            cols = tuple(a[idx] for a in arrays)
        return cls(*cols, start, w[order], ylo[order], yhi[order], xlo[order], xhi[order])

    @classmethod
    def concat(cls, parts: list[Trails]) -> Trails:
        """The parts' segments in one set, in increasing ``ylo`` (stable in the parts' order). Runs of segments
        that stay consecutive (a part merged with a few segments of another) are copied as slices."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        offs = np.cumsum([0] + [p.x.size for p in parts])
        seg = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("w", "ylo", "yhi", "xlo", "xhi")}
        bounds = np.concatenate([p.start[:-1] + o for p, o in zip(parts, offs)] + [offs[-1:]])
        order = np.argsort(seg["ylo"], kind="stable")
        # pieces of consecutive samples of one part: cut where the next segment is not the next one of its part
        part = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
        cut = np.flatnonzero((order[1:] != order[:-1] + 1) | (part[order[1:]] != part[order[:-1]])) + 1
        if cut.size > CONCAT_PIECES_MAX:
            cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("x", "y", "e", "t_lo", "t_hi")}
            return cls._take_runs(tuple(cat.values()), bounds, order, seg["w"], seg["ylo"], seg["yhi"], seg["xlo"],
                                  seg["xhi"])
        first, last = order[np.r_[0, cut]], order[np.r_[cut - 1, order.size - 1]]
        lo, hi = bounds[first], bounds[last + 1]  # each piece: samples lo:hi of the concatenation
        part_of = part[first]
        cols = []
        for k in ("x", "y", "e", "t_lo", "t_hi"):
            out = np.empty(int(offs[-1]), dtype=np.result_type(*[getattr(p, k) for p in parts]))
            pos = 0
            for a, b, j in zip(lo, hi, part_of):
                out[pos:pos + b - a] = getattr(parts[j], k)[a - offs[j]:b - offs[j]]
                pos += b - a
            cols.append(out)
        lens = np.diff(bounds)[order]
        start = np.r_[0, np.cumsum(lens)].astype(np.int64)
        return cls(*cols, start, *(seg[k][order] for k in ("w", "ylo", "yhi", "xlo", "xhi")))

    def sorted(self) -> Trails:
        """Segments in increasing ``ylo`` (samples reordered accordingly)."""
        order = np.argsort(self.ylo, kind="stable")
        if np.all(order == np.arange(order.size)):
            return self
        return Trails._take_runs((self.x, self.y, self.e, self.t_lo, self.t_hi), self.start, order, self.w, self.ylo,
                                 self.yhi, self.xlo, self.xhi)

    def __len__(self) -> int:
        return int(self.w.size)

    @property
    def n_samples(self) -> int:
        return int(self.x.size)

    def as_samples(self) -> Samples:
        """The samples as independent points (for a PSF without a separable form)."""
        w = np.repeat(self.w, np.diff(self.start))
        return Samples.concat([Samples(self.x, self.y, self.e, self.t_lo, self.t_hi, w)])


def partly_exposed(t_lo, t_hi, row_first, row_last, row_time_s: float, exptime_s: float) -> np.ndarray:
    """Indices of the samples whose interval ``[t_lo, t_hi]`` is not inside the exposure window of every row from
    ``row_first`` to ``row_last`` (:func:`window_overlap`). For the others the overlap is the interval itself on
    each of those rows, ``min(t_hi, t0 + T) - max(t_lo, t0) = t_hi - t_lo``, so the weight is exactly 1.0 (the
    same subtraction over itself; ``t0`` grows with the row, in floating point too)."""
    t0_first = np.asarray(row_first, dtype=float) * row_time_s
    t0_last = np.asarray(row_last, dtype=float) * row_time_s
    inside = (t_lo >= t0_last) & (t_hi <= t0_first + exptime_s) & (t_hi - t_lo > 0)
    return np.flatnonzero(~inside)


def render_trails(tr: Trails, psf, acc: np.ndarray, row0: int, col0: int, row_time_s: float = 0.0,
                  exptime_s: float = 0.0) -> None:
    """Add the segments reaching ``acc`` (rows row0.., cols col0..) as matrix products (separable PSF).

    The per-sample work (PSF factors, rolling-shutter weights, box indices) is done at once for all the
    band's segments of one stamp width, in chunks; only the matrix product is per segment.
    """
    if not len(tr):
        return
    nrow, ncol = acc.shape
    row1, col1 = row0 + nrow, col0 + ncol
    hmax = int(np.max(tr.yhi - tr.ylo))
    lo = int(np.searchsorted(tr.ylo, row0 - hmax, side="left"))
    hi = int(np.searchsorted(tr.ylo, row1, side="left"))
    ks = np.arange(lo, hi)
    ks = ks[(tr.yhi[ks] >= row0) & (tr.xhi[ks] >= col0) & (tr.xlo[ks] < col1)]
    for w in np.unique(tr.w[ks]):
        kw = ks[tr.w[ks] == w]
        # samples per chunk: the padded box matrices (<= 3 (2w + 1) columns each) stay ~TRAIL_CHUNK_ELEMENTS
        ends = np.cumsum(tr.start[kw + 1] - tr.start[kw])
        cap = max(1, TRAIL_CHUNK_ELEMENTS // (3 * (2 * int(w) + 1)))
        cut = np.searchsorted(ends, np.arange(cap, int(ends[-1]), cap), side="left")
        for part in np.split(kw, np.unique(cut + 1)):
            if part.size:
                _render_segments(tr, psf, acc, row0, col0, part, int(w), row_time_s, exptime_s)


def _render_segments(tr: Trails, psf, acc: np.ndarray, row0: int, col0: int, ks: np.ndarray, w: int,
                     row_time_s: float, exptime_s: float) -> None:
    """Segments ``ks`` (stamp half-width ``w``, each reaching ``acc``): S_box += EY^T diag(e f) EX each."""
    nrow, ncol = acc.shape
    a = tr.start[ks]
    n = tr.start[ks + 1] - a
    seg = np.repeat(np.arange(ks.size), n)  # segment of each sample (local number)
    idx = np.arange(int(n.sum())) + np.repeat(a - np.r_[0, np.cumsum(n)[:-1]], n)
    iy = np.rint(tr.y[idx])
    near = (iy + w >= row0) & (iy - w < row0 + nrow)  # samples whose stamp rows reach the band
    idx, seg = idx[near], seg[near]
    offs = np.r_[0, np.cumsum(np.bincount(seg, minlength=ks.size))]
    off = np.arange(-w, w + 1)
    x, y = tr.x[idx], tr.y[idx]
    cols = np.rint(x).astype(np.int64)[:, None] + off
    rows = np.rint(y).astype(np.int64)[:, None] + off
    ex, ey = psf.factors(x, y, cols - x[:, None], rows - y[:, None], stamp=True)  # consecutive pixels
    ey = ey * tr.e[idx, None]
    if row_time_s > 0:
        part = partly_exposed(tr.t_lo[idx], tr.t_hi[idx], rows[:, 0], rows[:, -1], row_time_s, exptime_s)
        if part.size:  # the others' weights are exactly 1 on every row of their stamps
            ey[part] *= window_overlap(tr.t_lo[idx[part], None], tr.t_hi[idx[part], None], rows[part], row_time_s,
                                       exptime_s)
    r_lo = np.maximum(row0, tr.ylo[ks])
    r_hi = np.minimum(row0 + nrow, tr.yhi[ks] + 1)
    c_lo = np.maximum(col0, tr.xlo[ks])
    c_hi = np.minimum(col0 + ncol, tr.xhi[ks] + 1)
    by, bx = r_hi - r_lo, c_hi - c_lo
    BY, BX = int(by.max()), int(bx.max())
    N = idx.size
    EY = np.zeros((N, BY + 1))  # column BY (BX) collects what falls outside the box (discarded)
    EX = np.zeros((N, BX + 1))
    for E, v, pos, lo_, size, last in ((EY, ey, rows, r_lo, by, BY), (EX, ex, cols, c_lo, bx, BX)):
        i = pos - lo_[seg, None]
        i = np.where((i >= 0) & (i < size[seg, None]), i, last)
        i += (np.arange(N) * (last + 1))[:, None]  # flat index: one 1-D scatter (2x faster than 2-D)
        E.reshape(-1)[i.reshape(-1)] = v.reshape(-1)  # distinct inside the box; repeats only in the discard column
    for j in np.flatnonzero(offs[1:] > offs[:-1]):
        s0, s1 = offs[j], offs[j + 1]
        box = acc[r_lo[j] - row0:r_hi[j] - row0, c_lo[j] - col0:c_hi[j] - col0]
        box += EY[s0:s1, :by[j]].T @ EX[s0:s1, :bx[j]]


@dataclass
class SourceSignal:
    """Expected photo-electrons per unbinned pixel over the exposure: ``signal(y0, y1, x0, x1)``.

    The callable the detector chain consumes (``detector.chain.Signal``): sensor coordinates in, a
    float32 tile out; thread-safe (read-only state). ``background_e`` is the uniform part (sky, flat
    screen) [e-/pixel]; vignetting, flat-field response and dark signal are applied by the chain.

    Attributes
    ----------
    samples : the y-sorted :class:`Samples` of every source
    psf : pixel-integrated PSF (``scenes.image.psf``)
    background_e : uniform signal [e-/pixel]
    roi_y0, roi_x0 : sensor coordinates of the read-out window's first row and column
    row_time_s, exptime_s : rolling-shutter row delay tau and exposure time T [s]
    extra : optional smooth signal ``extra(y0, y1, x0, x1)`` [e-/pixel] in sensor coordinates (straylight)
    """

    samples: Samples
    psf: object
    background_e: float = 0.0
    roi_y0: int = 0
    roi_x0: int = 0
    row_time_s: float = 0.0
    exptime_s: float = 0.0
    meta: dict = field(default_factory=dict)
    trails: Trails = field(default_factory=Trails.empty)
    extra: object = None

    def __post_init__(self):
        if len(self.trails) and not hasattr(self.psf, "factors"):  # non-separable PSF: point samples
            self.samples = Samples.concat([self.samples, self.trails.as_samples()])
            self.trails = Trails.empty()

    @property
    def n_samples(self) -> int:
        return len(self.samples) + self.trails.n_samples

    def __call__(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        r0, c0 = y0 - self.roi_y0, x0 - self.roi_x0
        acc = render_samples(self.samples, self.psf, r0, y1 - self.roi_y0, c0, x1 - self.roi_x0,
                             self.row_time_s, self.exptime_s)
        render_trails(self.trails, self.psf, acc, r0, c0, self.row_time_s, self.exptime_s)
        if self.extra is not None:
            acc += self.extra(y0, y1, x0, x1)
        # float32(acc) + float32(background) in one pass: the sum rounded from the rounded terms, as in two passes
        return np.add(acc, np.float32(self.background_e), dtype=np.float32, casting="unsafe")

    def image(self, shape: tuple[int, int]) -> np.ndarray:
        """The whole read-out window (rows, cols) at once, float32 (for tests and small frames)."""
        return self(self.roi_y0, self.roi_y0 + shape[0], self.roi_x0, self.roi_x0 + shape[1])
