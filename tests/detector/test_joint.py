"""The joint series solver (detector.joint) against an independent stacked least squares."""

import numpy as np

from detector.joint import FrameGram, fixed_score, leave_one_out, solve_joint


def _gram(z: np.ndarray, r: np.ndarray, w: np.ndarray, ts: int, tp: int, ls: int, lf: int) -> FrameGram:
    zw = z * w
    return FrameGram(zw @ z.T, zw @ r, float(r @ (w * r)), ts, tp, ls, lf, r.size)


def _frames(rng, n_frames=4, n=400):
    """Frames with one shared template (coefficient 0.7), one own template per frame, one shared level and
    one own level; returns per-frame (Z, r, w) with Z rows [ts, tp, ls, lf]."""
    out = []
    for f in range(n_frames):
        x = np.linspace(-1, 1, n)
        shared_t = (1 + f) * x ** 2  # scales with the frame (e.g. exposure)
        own_t = np.sin(3 * x + f)
        shared_lv = np.full(n, 1.0 + 0.5 * f)
        own_lv = np.ones(n) * (f % 2 + 1) + x
        w = rng.uniform(0.5, 2.0, n)
        r = 0.7 * shared_t + (0.2 * f - 0.3) * own_t + 0.05 * shared_lv + (0.1 - 0.03 * f) * own_lv \
            + rng.normal(0, 1, n) / np.sqrt(w)
        out.append((np.stack([shared_t, own_t, shared_lv, own_lv]), r, w))
    return out


def test_joint_solution_is_the_stacked_weighted_least_squares():
    rng = np.random.default_rng(3)
    frames = _frames(rng)
    grams = [_gram(z, r, w, 1, 1, 1, 1) for z, r, w in frames]
    sol = solve_joint(grams)
    # independent: one big design matrix, shared columns common, own columns block-diagonal
    nf = len(frames)
    cols = 2 + 2 * nf
    blocks, ys, ws = [], [], []
    for i, (z, r, w) in enumerate(frames):
        x = np.zeros((r.size, cols))
        x[:, 0], x[:, 1] = z[0], z[2]
        x[:, 2 + 2 * i], x[:, 3 + 2 * i] = z[1], z[3]
        blocks.append(x), ys.append(r), ws.append(w)
    x, y, w = np.vstack(blocks), np.concatenate(ys), np.concatenate(ws)
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
    chi2 = float(np.sum(w * (y - x @ coef) ** 2))
    assert np.allclose(sol.shared, coef[0], rtol=1e-8)
    assert np.allclose(sol.shared_levels, coef[1], rtol=1e-6)
    for i in range(nf):
        assert np.allclose(sol.own[i], coef[2 + 2 * i], rtol=1e-6)
        assert np.allclose(sol.own_levels[i], coef[3 + 2 * i], rtol=1e-6)
    assert np.isclose(sol.chi2, chi2, rtol=1e-9)
    # the levels-only chi2 is the same problem without the template columns
    keep = [1] + [3 + 2 * i for i in range(nf)]
    c0, *_ = np.linalg.lstsq(x[:, keep] * sw[:, None], y * sw, rcond=None)
    assert np.isclose(sol.chi2_levels, float(np.sum(w * (y - x[:, keep] @ c0) ** 2)), rtol=1e-9)
    # the per-frame shares add up to the joint improvement (own templates count with the frame)
    assert np.isclose(sum(sol.per_frame_delta), sol.delta_chi2, rtol=1e-6)
    assert abs(sol.shared[0] - 0.7) < 0.05


def test_fixed_score_matches_a_direct_refit():
    rng = np.random.default_rng(5)
    z, r, w = _frames(rng, 1)[0]
    fg = _gram(z, r, w, 1, 1, 1, 1)
    c = np.array([0.6, 0.04])
    got = fixed_score(fg, [0, 2], c, [1, 3])
    y = r - c @ z[[0, 2]]
    sw = np.sqrt(w)
    b, *_ = np.linalg.lstsq(z[[1, 3]].T * sw[:, None], y * sw, rcond=None)
    assert np.isclose(got, float(np.sum(w * (y - b @ z[[1, 3]]) ** 2)), rtol=1e-9)


def test_leave_one_out_rewards_a_shared_pattern_and_not_noise():
    rng = np.random.default_rng(7)
    frames = _frames(rng)
    there = sum(leave_one_out([_gram(z, r, w, 1, 1, 1, 1) for z, r, w in frames]))
    assert there < -100  # the shared x^2 pattern predicts the frames it never saw
    # the same templates on frames without them: a held-out score near zero or positive, not a gain
    # (the shared template alone: an own template's in-frame gain is not a held-out score)
    noise = [(z[[0, 2, 3]], r - 0.7 * z[0] - (0.2 * f - 0.3) * z[1], w) for f, (z, r, w) in enumerate(frames)]
    absent = sum(leave_one_out([_gram(z, r, w, 1, 0, 1, 1) for z, r, w in noise]))
    assert absent > -10


def test_sample_grams_equal_the_chunked_frame_gram():
    """The cached-levels Gram of a sample (the variant search) is the chunked one (the final refit)."""
    from detector.joint import SampleGrams, frame_gram
    from detector.signatures import Residuals, SpikeStats
    from helpers import small_sensor

    rng = np.random.default_rng(2)
    s = small_sensor(width=64, height=48)
    shape = (48, 64)
    model = np.full(shape, 1000.0, np.float32)
    photo = rng.uniform(100, 200, shape).astype(np.float32)
    res = Residuals((model + rng.normal(0, 5, shape)).astype(np.float32), model, np.full(shape, 25.0, np.float32),
                    np.ones(shape, bool), photo, np.full(shape, 2.0, np.float32), np.arange(48.0), np.arange(64.0),
                    s, 10.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))
    idx, _, w = res.flat_profiled()
    r = res.flat()[1]
    t = np.linspace(-1, 1, shape[0] * shape[1])

    def tmpl(i):
        return np.stack([t[i], t[i] ** 2])

    a = frame_gram(res, idx, r, w, shared=tmpl, shared_levels=["light_scale"])
    b = SampleGrams(res, idx, r, w, shared_levels=["light_scale"]).gram(shared=tmpl)
    assert np.allclose(a.g, b.g, rtol=1e-10) and np.allclose(a.z, b.z, rtol=1e-10) and np.isclose(a.rr, b.rr)
    assert (a.ts, a.tp, a.ls, a.lf) == (b.ts, b.tp, b.ls, b.lf)
