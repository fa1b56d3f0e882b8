"""Joint linear fits over the frames of a series: shared parameters, per-frame nuisance levels.

A linear signature (:class:`detector.signatures.LinearSignature`) describes an effect as templates whose
coefficients are the effect's physical parameters, each template built by the frame's own model: a dark
charge scales with the frame's exposure time, a response with the frame's light, a bias structure with
nothing. Hardware the frames share therefore has ONE set of coefficients for the whole series; the global
levels a model knows only roughly (light, sky, bias offset, dark level, :meth:`Residuals.levels`) are either
per frame (a sky, a bias drift) or shared (a lamp's calibration, the dark current at the sensor's
temperature); an effect that changes from frame to frame (a straylight that moves with the pointing) has
its own coefficients in every frame.

Everything is solved from each frame's normal equations (Gram matrices of the columns
``[shared templates, shared levels | per-frame levels, per-frame templates]``, accumulated in chunks of
pixels): the per-frame columns are profiled out frame by frame and the shared ones solved from the summed
systems (Frisch-Waugh-Lovell; the weighted least squares of the stacked frames, e.g. Bjorck 1996,
Numerical Methods for Least Squares Problems, sect. 6.3 on block-angular problems). A leave-one-frame-out
score (the shared coefficients fitted on the other frames, scored on the left-out one with its own levels
refitted) falls out of the same matrices: a hardware effect that is really there predicts the frame it
never saw (Arlot & Celisse 2010, Stat. Surveys 4, 40).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .signatures import CHUNK_PIXELS, Residuals, template_at

Values = Callable[[np.ndarray], np.ndarray]


@dataclass
class FrameGram:
    """One frame's normal equations over the columns ``[ts shared templates, tp per-frame templates,
    ls shared levels, lf per-frame levels]``: ``g = Z'WZ``, ``z = Z'Wr``, ``rr = r'Wr`` (weights and
    residual of :meth:`Residuals.flat_profiled` / :meth:`Residuals.flat`)."""

    g: np.ndarray
    z: np.ndarray
    rr: float
    ts: int
    tp: int
    ls: int
    lf: int
    n: int  #: pixels

    def cols(self, which: str) -> list[int]:
        a = {"ts": 0, "tp": self.ts, "ls": self.ts + self.tp, "lf": self.ts + self.tp + self.ls}[which]
        return list(range(a, a + getattr(self, which)))


def level_columns(res: Residuals, shared: Sequence[str]) -> tuple[list, list]:
    """The frame's level templates split into the shared ones (in the order of ``shared``; a level the frame
    does not fit gives a zero column) and its own (the other levels it fits)."""
    temps, keep = res.level_templates(), res.levels()["keep"]
    names = [res.LEVELS[i] for i in keep]
    sh = [temps[res.LEVELS.index(n)] if n in names else np.zeros(1, np.float32) for n in shared]
    own = [temps[i] for i, n in zip(keep, names) if n not in shared]
    return sh, own


def frame_gram(res: Residuals, idx: np.ndarray, r: np.ndarray, w: np.ndarray, shared: Values | None = None,
               own: Values | None = None, shared_levels: Sequence[str] = ()) -> FrameGram:
    """The normal equations of one frame (accumulated in chunks of CHUNK_PIXELS pixels): templates shared by
    the series (``shared(idx)`` -> (k, pixels)), the frame's own templates (``own``), the shared levels and
    the frame's own levels, at the fitted pixels ``idx`` with residual ``r`` and weights ``w``."""
    shape = res.data_adu.shape
    lsh, lown = level_columns(res, shared_levels)
    g = z = None
    rr = 0.0
    ts = tp = 0
    for a in range(0, idx.size, CHUNK_PIXELS):
        sl = slice(a, a + CHUNK_PIXELS)
        ii = idx[sl]
        parts = []
        if shared is not None:
            t = np.atleast_2d(np.asarray(shared(ii), np.float64))
            ts = t.shape[0]
            parts.append(t)
        if own is not None:
            t = np.atleast_2d(np.asarray(own(ii), np.float64))
            tp = t.shape[0]
            parts.append(t)
        parts += [np.stack([template_at(t, shape, ii) for t in lv]) for lv in (lsh, lown) if lv]
        zz = np.concatenate(parts) if parts else np.zeros((0, ii.size))
        zw = zz * w[sl]
        gg, zr = zw @ zz.T, zw @ r[sl]
        g = gg if g is None else g + gg
        z = zr if z is None else z + zr
        rr += float(np.dot(r[sl] * w[sl], r[sl]))
    m = ts + tp + len(lsh) + len(lown)
    if g is None:
        g, z = np.zeros((m, m)), np.zeros(m)
    return FrameGram(g, z, rr, ts, tp, len(lsh), len(lown), int(idx.size))


class SampleGrams:
    """:func:`frame_gram` for many templates on one frame's fixed sample of pixels: the levels' columns and
    their Gram matrix are computed once (they do not depend on the template), each template's only its own
    products. ``scale`` multiplies everything (a subsample standing for all fitted pixels)."""

    def __init__(self, res: Residuals, idx: np.ndarray, r: np.ndarray, w: np.ndarray,
                 shared_levels: Sequence[str] = (), scale: float = 1.0):
        shape = res.data_adu.shape
        lsh, lown = level_columns(res, shared_levels)
        self.ls, self.lf = len(lsh), len(lown)
        self.lv = (np.stack([template_at(t, shape, idx) for t in (*lsh, *lown)]) if lsh or lown
                   else np.zeros((0, idx.size)))
        self.idx, self.r, self.w, self.scale = idx, r, w, scale
        lw = self.lv * w
        self.ll, self.lr = lw @ self.lv.T, lw @ r
        self.rr = float(np.dot(r * w, r))

    def gram(self, shared: Values | None = None, own: Values | None = None) -> FrameGram:
        parts = [np.atleast_2d(np.asarray(f(self.idx), np.float64)) for f in (shared, own) if f is not None]
        ts = parts[0].shape[0] if shared is not None else 0
        tp = parts[-1].shape[0] if own is not None else 0
        t = np.concatenate(parts) if parts else np.zeros((0, self.idx.size))
        tw = t * self.w
        k, m = t.shape[0], t.shape[0] + self.lv.shape[0]
        g, z = np.empty((m, m)), np.empty(m)
        g[:k, :k], g[:k, k:] = tw @ t.T, tw @ self.lv.T
        g[k:, :k], g[k:, k:] = g[:k, k:].T, self.ll
        z[:k], z[k:] = tw @ self.r, self.lr
        s = self.scale
        return FrameGram(g * s, z * s, self.rr * s, ts, tp, self.ls, self.lf, int(self.idx.size * s))


def _solve(g: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``g^-1 b`` for a symmetric positive semi-definite ``g``, robust to degenerate columns (a template that
    is a combination of others carries no information: its share is set by the pseudo-inverse)."""
    if g.size == 0:
        return np.zeros(b.shape)
    d = np.sqrt(np.maximum(np.diag(g), 0.0))
    s = np.where(d > 0, d, 1.0)
    gn = g / np.outer(s, s)
    x = np.linalg.pinv(gn, rcond=1e-10, hermitian=True) @ (b / (s if b.ndim == 1 else s[:, None]))
    return x / (s if b.ndim == 1 else s[:, None])


def _profile(fg: FrameGram, keep: list[int], prof: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """The frame's system in the ``keep`` columns once the ``prof`` columns are profiled out:
    ``A = G_kk - G_kp G_pp^-1 G_pk``, ``b = z_k - G_kp G_pp^-1 z_p``, ``rr - z_p' G_pp^-1 z_p``."""
    g, z = fg.g, fg.z
    gkk, zk = g[np.ix_(keep, keep)], z[keep]
    if not prof:
        return gkk, zk, fg.rr
    gpp, gpk, zp = g[np.ix_(prof, prof)], g[np.ix_(prof, keep)], z[prof]
    x = _solve(gpp, np.column_stack([gpk, zp]) if keep else zp[:, None])
    kx, kz = (x[:, :-1], x[:, -1]) if keep else (np.zeros((len(prof), 0)), x[:, 0])
    return gkk - gpk.T @ kx, zk - gpk.T @ kz, float(fg.rr - zp @ kz)


@dataclass
class JointFit:
    """The joint solution: shared template coefficients, each frame's own template coefficients and levels,
    the shared levels (with the templates, and without them: ``levels_only``), and ``delta_chi2`` (the
    templates' improvement over the levels alone, summed over frames; ``per_frame_delta`` its share in each
    frame, the shared levels held at their joint values and the frame's own levels refitted)."""

    shared: np.ndarray
    own: list[np.ndarray]
    shared_levels: np.ndarray
    own_levels: list[np.ndarray]
    chi2: float
    chi2_levels: float
    per_frame_delta: list[float]
    levels_only: np.ndarray

    @property
    def delta_chi2(self) -> float:
        return self.chi2 - self.chi2_levels


def _joint_system(grams: Sequence[FrameGram], with_templates: bool, skip: int | None = None):
    """The summed system of the shared columns (templates and levels, or levels only) with each frame's own
    columns profiled out; ``skip``: leave that frame out."""
    a = b = None
    rr = 0.0
    for i, fg in enumerate(grams):
        if i == skip:
            continue
        keep = (fg.cols("ts") if with_templates else []) + fg.cols("ls")
        prof = (fg.cols("tp") if with_templates else []) + fg.cols("lf")
        ai, bi, ri = _profile(fg, keep, prof)
        a, b = (ai, bi) if a is None else (a + ai, b + bi)
        rr += ri
    return a, b, rr


def _solve_system(a, b, rr) -> tuple[np.ndarray, float]:
    c = _solve(a, b) if a is not None and a.size else np.zeros(0)
    return c, float(rr - (b @ c if c.size else 0.0))


def fixed_score(fg: FrameGram, fixed: list[int], c: np.ndarray, free: list[int]) -> float:
    """chi2 of one frame with the ``fixed`` columns at coefficients ``c`` and the ``free`` ones refitted:
    ``(r - X c)' W (r - X c) - z1' G_ff^-1 z1`` with ``z1 = z_f - G_fx c`` (from the frame's Gram alone)."""
    g, z = fg.g, fg.z
    rr = fg.rr
    if fixed:
        rr = rr - 2 * float(c @ z[fixed]) + float(c @ g[np.ix_(fixed, fixed)] @ c)
    if not free:
        return float(rr)
    z1 = z[free] - (g[np.ix_(free, fixed)] @ c if fixed else 0.0)
    return float(rr - z1 @ _solve(g[np.ix_(free, free)], z1))


def _frame_delta(fg: FrameGram, c_full: np.ndarray, c_levels: np.ndarray) -> float:
    """The frame's chi2 with the shared templates and levels at ``c_full`` minus with the shared levels at
    ``c_levels`` (templates absent); its own levels (and own templates) refitted in both."""
    after = fixed_score(fg, fg.cols("ts") + fg.cols("ls"), c_full, fg.cols("tp") + fg.cols("lf"))
    before = fixed_score(fg, fg.cols("ls"), c_levels, fg.cols("lf"))
    return after - before


def levels_chi2(grams: Sequence[FrameGram]) -> tuple[float, np.ndarray]:
    """chi2 of the series with the levels alone (shared ones joint, each frame's own profiled)."""
    c, chi2 = _solve_system(*_joint_system(grams, False))
    return chi2, c


def solve_joint(grams: Sequence[FrameGram]) -> JointFit:
    """Solve the series: shared templates and shared levels from the summed per-frame systems (each frame's
    levels and own templates profiled out), then each frame's own columns back-substituted."""
    c, chi2 = _solve_system(*_joint_system(grams, True))
    c_lv, chi2_lv = _solve_system(*_joint_system(grams, False))
    ts = grams[0].ts if grams else 0
    own, own_lv, per = [], [], []
    for fg in grams:
        keep, prof = fg.cols("ts") + fg.cols("ls"), fg.cols("tp") + fg.cols("lf")
        zp = fg.z[prof] - (fg.g[np.ix_(prof, keep)] @ c if keep else 0.0)
        x = _solve(fg.g[np.ix_(prof, prof)], zp) if prof else np.zeros(0)
        own.append(x[:fg.tp])
        own_lv.append(x[fg.tp:])
        per.append(_frame_delta(fg, c, c_lv))
    return JointFit(c[:ts], own, c[ts:], own_lv, chi2, chi2_lv, per, c_lv)


def leave_one_out(grams: Sequence[FrameGram]) -> list[float]:
    """Leave-one-frame-out scores of the shared templates: for each frame, the shared coefficients and
    shared levels fitted on the OTHER frames (with the templates, and without them for the reference),
    scored on the left-out frame with only its own levels (and own templates) refitted
    (:func:`_frame_delta`). Their sum is a held-out delta chi2: negative when the shared pattern predicts
    frames it never saw."""
    out = []
    for i, fg in enumerate(grams):
        c, _ = _solve_system(*_joint_system(grams, True, skip=i))
        c_lv, _ = _solve_system(*_joint_system(grams, False, skip=i))
        out.append(_frame_delta(fg, c, c_lv))
    return out


def frame_amplitude(fg: FrameGram, sol: JointFit) -> tuple[float, float]:
    """The shared templates' combination ``T c`` (the joint fit's pattern) fitted to one frame alone, its
    shared levels held at the joint values and its own levels refitted: (amplitude relative to the joint
    fit, its standard error). 1 where the frame agrees with the joint fit."""
    t, ls, free = fg.cols("ts"), fg.cols("ls"), fg.cols("tp") + fg.cols("lf")
    if not t:
        return float("nan"), float("nan")
    g, z, c, s = fg.g, fg.z, sol.shared, sol.shared_levels
    zu = float(c @ z[t]) - (float(c @ g[np.ix_(t, ls)] @ s) if ls else 0.0)
    guu = float(c @ g[np.ix_(t, t)] @ c)
    if free:
        zf = z[free] - (g[np.ix_(free, ls)] @ s if ls else 0.0)
        guf = g[np.ix_(free, t)] @ c
        x = _solve(g[np.ix_(free, free)], np.column_stack([guf, zf]))
        zu -= float(guf @ x[:, 1])
        guu -= float(guf @ x[:, 0])
    if guu <= 0:
        return float("nan"), float("nan")
    return zu / guu, 1.0 / math.sqrt(guu)
