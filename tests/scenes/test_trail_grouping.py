"""The trails' grouping (``Trails.from_samples``, ``Trails.concat``) gathers the samples once, in their final
order: the same arrays as the plain formula it replaces (a stable sort of the samples by key, segments then
stably sorted by their first row); the stamps' pixel fractions are filled in one buffer: the same numbers as the
concatenated edges (docs/performance.md, "Third round")."""

from itertools import pairwise

import numpy as np
import pytest

from scenes.image import signal
from scenes.image.signal import Trails

FIELDS = ("x", "y", "e", "t_lo", "t_hi", "start", "w", "ylo", "yhi", "xlo", "xhi")


def _plain(x, y, e, t_lo, t_hi, w, key) -> dict:
    """Stable sort by key, segments' boxes, then the segments stably by ylo (the formula replaced)."""
    o = np.argsort(key, kind="stable")
    x, y, e, t_lo, t_hi, w, key = (a[o] for a in (x, y, e, t_lo, t_hi, w, key))
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    bounds = np.r_[start, x.size]
    segs = []
    for a, b in pairwise(bounds):
        ws = int(w[a])
        iy, ix = np.rint(y[a:b]).astype(np.int64), np.rint(x[a:b]).astype(np.int64)
        segs.append((iy.min() - ws, a, b, ws, iy.max() + ws, ix.min() - ws, ix.max() + ws))
    segs.sort(key=lambda s: s[0])  # list.sort is stable
    return _assemble(segs, (x, y, e, t_lo, t_hi))


def _assemble(segs, arrays) -> dict:
    out = {k: np.concatenate([a[s[1]:s[2]] for s in segs]) for k, a in zip(FIELDS[:5], arrays)}
    out["start"] = np.r_[0, np.cumsum([s[2] - s[1] for s in segs])]
    for k, i in (("w", 3), ("ylo", 0), ("yhi", 4), ("xlo", 5), ("xhi", 6)):
        out[k] = np.array([s[i] for s in segs], dtype=np.int64)
    return out


def _check(tr: Trails, expected: dict) -> None:
    for k in FIELDS:
        got = getattr(tr, k)
        assert np.array_equal(got, expected[k]), k
        assert got.dtype == np.asarray(expected[k]).dtype or k == "start", k


def _samples(rng, n, runs: bool):
    x, y = rng.uniform(-20, 300, n), rng.uniform(-20, 300, n)
    e, t = rng.uniform(0, 5, n), rng.uniform(0, 1, n)
    if runs:  # each key one contiguous run (a star's samples in time order), keys in any order
        lens = rng.multinomial(n, np.ones(9) / 9)
        lens = lens[lens > 0]
        key = np.repeat(rng.permutation(2 * lens.size)[:lens.size], lens)
        w = np.repeat(rng.integers(3, 9, lens.size), lens)
    else:  # a key in several runs
        key, w = rng.integers(0, 7, n), rng.integers(3, 9, n)
    return x, y, e, t, t + 0.1, w, key


@pytest.mark.parametrize("runs", [True, False])
def test_from_samples_equals_the_sort_by_key_then_by_first_row(runs):
    rng = np.random.default_rng(4 + runs)
    for _ in range(40):
        cols = _samples(rng, int(rng.integers(1, 300)), runs)
        _check(Trails.from_samples(*cols), _plain(*cols))


@pytest.mark.parametrize("pieces_max", [64, 0])
def test_concat_equals_the_stable_merge_of_the_parts_segments(monkeypatch, pieces_max):
    """Copied as slices (few pieces) or gathered (``CONCAT_PIECES_MAX`` = 0): the segments of all parts stably
    sorted by ylo, each with its own samples."""
    monkeypatch.setattr(signal, "CONCAT_PIECES_MAX", pieces_max)
    rng = np.random.default_rng(9)
    for _ in range(30):
        parts = [Trails.from_samples(*_samples(rng, int(rng.integers(1, 200)), bool(rng.integers(2))))
                 for _ in range(int(rng.integers(2, 5)))]
        segs, arrays, off = [], [], 0
        for p in parts:
            for k in range(len(p)):
                a, b = int(p.start[k]) + off, int(p.start[k + 1]) + off
                segs.append((p.ylo[k], a, b, p.w[k], p.yhi[k], p.xlo[k], p.xhi[k]))
            off += p.x.size
        arrays = [np.concatenate([getattr(p, k) for p in parts]) for k in FIELDS[:5]]
        segs.sort(key=lambda s: s[0])
        _check(Trails.concat(parts), _assemble(segs, arrays))


def test_stamp_fractions_from_one_buffer_equal_the_concatenated_edges():
    """gaussian_pixel_fractions(stamp=True): Phi at the edges d - 1/2 and the last d + 1/2, scaled by 1/sigma,
    differenced (eq. 52), bit for bit the formula with the concatenated edges."""
    from scipy.special import ndtr

    from scenes.image.psf import gaussian_pixel_fractions

    rng = np.random.default_rng(1)
    x = rng.uniform(-50.0, 5000.0, 500)
    d = (np.rint(x)[:, None] + np.arange(-13, 14)) - x[:, None]
    for sigma in (0.4, 1.314, 3.7):
        edges = np.concatenate([d - 0.5, d[:, -1:] + 0.5], axis=1)
        edges *= 1.0 / sigma
        cdf = ndtr(edges)
        expected = cdf[:, 1:] - cdf[:, :-1]
        assert np.array_equal(gaussian_pixel_fractions(d, sigma, stamp=True), expected)
        assert np.array_equal(gaussian_pixel_fractions(d, sigma), expected)  # the steps tested: the same path


def test_samples_inside_every_rows_window_have_weights_of_exactly_one():
    """partly_exposed names every sample whose rolling-shutter weights (window_overlap over its stamp's rows) are
    not all exactly 1.0; the others' weights are 1.0 bit for bit, so their rows are left as they are."""
    from scenes.image.motion import window_overlap
    from scenes.image.signal import partly_exposed

    rng = np.random.default_rng(3)
    tau, T, w = 4.7e-5, 2.0, 13
    for dt in (2.0 / 142, 1e-4, 0.3):
        t = rng.uniform(-0.05, 2.6, 20_000)
        t_lo, t_hi = t - dt / 2, t + dt / 2
        rows = rng.integers(-20, 10_700, t.size)[:, None] + np.arange(-w, w + 1)
        f = window_overlap(t_lo[:, None], t_hi[:, None], rows, tau, T)
        part = partly_exposed(t_lo, t_hi, rows[:, 0], rows[:, -1], tau, T)
        whole = np.setdiff1d(np.arange(t.size), part)
        assert np.all(f[whole] == 1.0)
        clearly_inside = (t_lo[part] > rows[part, -1] * tau + 1e-9) & (t_hi[part] < rows[part, 0] * tau + T - 1e-9)
        assert not np.any(clearly_inside)  # only samples at a window's edge are weighted
        assert 0 < part.size < t.size


def test_source_signal_tile_is_the_float32_sum_of_the_rounded_terms():
    """SourceSignal's tile in one pass: float32(sources) + float32(background), bit for bit the two-pass form."""
    from scenes.image.psf import GaussianPSF
    from scenes.image.signal import Samples, SourceSignal, render_samples

    rng = np.random.default_rng(8)
    n = 300
    inf = np.full(n, np.inf)
    s = Samples.concat([Samples(rng.uniform(0, 200, n), rng.uniform(0, 120, n), rng.uniform(1, 1e5, n), -inf, inf,
                                np.full(n, 7))])
    for bg in (0.0, 46.7, 3.3e-3):
        sig = SourceSignal(s, GaussianPSF(2.2), background_e=bg)
        expected = render_samples(s, sig.psf, 0, 120, 0, 200).astype(np.float32)
        expected += np.float32(bg)
        got = sig(0, 120, 0, 200)
        assert got.dtype == np.float32 and np.array_equal(got, expected)
