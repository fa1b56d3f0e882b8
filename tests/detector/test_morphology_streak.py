"""A straight streak of the residual (detector.morphology.straight_line): the ``streak`` word of the
``residual_morphology`` vocabulary.

Independent references: the best of the n lines searched in white noise is a normal deviate below the look-
elsewhere bar ``isf(0.5e-3 / n)`` (the bar's own false-alarm rate is checked on 40 noise maps); a Gaussian trail
drawn between two known points (as :class:`scenes.app.validation.unseen.SatelliteTrail` draws one) is found at
its angle, with its length, its peak and its FWHM (2.355 sigma) measured within a pixel or a few per cent; a
sinusoid along the rows (a pattern of lines) is no streak; and on a whole frame a trail is described as one."""

import math

import numpy as np
import pytest

from detector.morphology import describe, is_streak, straight_line, streak_bar


def _trail(shape, p0, p1, sigma, amp):
    """A segment from p0 = (x, y) to p1 with a Gaussian cross-section of ``sigma`` px, ``amp`` at its centre."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    (x0, y0), (x1, y1) = p0, p1
    dx, dy = x1 - x0, y1 - y0
    t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / (dx * dx + dy * dy), 0.0, 1.0)
    d = np.hypot(xx - (x0 + t * dx), yy - (y0 + t * dy))
    return amp * np.exp(-0.5 * (d / sigma) ** 2)


def test_white_noise_stays_below_the_bar():
    rng = np.random.default_rng(7)
    w = np.ones((192, 224))
    over = 0
    for _ in range(40):
        line = straight_line(rng.standard_normal(w.shape), w)
        over += line["sigma_searched"] >= streak_bar(line["n_tests"])
    # a per-frame false alarm of 1e-3: none of 40 (binomial: 4 % chance of one or more)
    assert over == 0


@pytest.mark.parametrize("shape,p0,p1,sigma,amp", [((256, 256), (51, 77), (205, 154), 1.5, 1.0),
                                                    ((300, 520), (500, 20), (90, 260), 1.0, 1.5),
                                                    ((1024, 1024), (100, 900), (700, 300), 2.0, 0.8)])
def test_a_trail_is_found_with_its_geometry(shape, p0, p1, sigma, amp):
    rng = np.random.default_rng(3)
    r = rng.standard_normal(shape) + _trail(shape, p0, p1, sigma, amp)
    line = straight_line(r, np.ones(shape))
    assert is_streak(line)
    (x0, y0), (x1, y1) = p0, p1
    angle = math.degrees(math.atan2(y1 - y0, x1 - x0)) % 180.0
    assert abs((line["angle_deg"] - angle + 90) % 180 - 90) < 0.5
    assert abs(line["length_px"] - math.hypot(x1 - x0, y1 - y0)) < 0.05 * math.hypot(x1 - x0, y1 - y0) + 16
    assert abs(line["peak_adu"] - amp) < 0.15 * amp
    assert abs(line["fwhm_px"] - 2.355 * sigma) <= 1.5
    # the point given lies on the line: its distance to the true line below a pixel
    x, y = line["through"]
    dist = abs((x - x0) * (y1 - y0) - (y - y0) * (x1 - x0)) / math.hypot(x1 - x0, y1 - y0)
    assert dist < 1.0


def test_a_dark_trail_is_found_too():
    shape = (256, 256)
    r = np.random.default_rng(4).standard_normal(shape) - _trail(shape, (10, 30), (240, 200), 1.2, 1.2)
    line = straight_line(r, np.ones(shape))
    assert is_streak(line) and line["peak_adu"] < 0


def test_a_pattern_of_lines_is_no_streak():
    """A sinusoid along the rows (a pick-up, 23 rows period, 1 sigma): every crest is as strong as the best."""
    shape = (256, 256)
    yy = np.arange(shape[0], dtype=float)[:, None] * np.ones((1, shape[1]))
    r = np.random.default_rng(5).standard_normal(shape) + np.sin(2 * np.pi * yy / 23.0)
    line = straight_line(r, np.ones(shape))
    assert line["sigma_searched"] >= streak_bar(line["n_tests"]) and not is_streak(line)


def test_a_trail_on_a_frame_is_described_as_a_streak():
    """A trail of 3 sigma at its centre across a 256^2 flat frame's residual (without row noise)."""
    from test_morphology_rows import OWN_VAR, _frame

    trail = _trail((256, 256), (20, 60), (230, 140), 1.3, 3.0 * math.sqrt(OWN_VAR))
    m = describe(_frame(0, row_var=1e-9, extra=trail))
    assert m["significant"] and m["geometry"][0] == "streak", m["explanation"]
    assert "trail" in m["explanation"]
    assert m["empirical"] is not None and m["empirical"].get("form") == "streak"


def test_a_compact_blob_is_no_streak():
    """A round residual (a star's misfit: 3 px, 8 sigma peak) passes the line bar but is not elongated."""
    shape = (256, 256)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    blob = 8.0 * np.exp(-0.5 * ((yy - 100) ** 2 + (xx - 140) ** 2) / 3.0 ** 2)
    line = straight_line(np.random.default_rng(6).standard_normal(shape) + blob, np.ones(shape))
    assert line["sigma_searched"] >= streak_bar(line["n_tests"]) and not is_streak(line)



@pytest.mark.parametrize("row_var", [1e-9, "rows"])
def test_a_trail_too_faint_to_move_the_frames_chi2_is_still_a_streak(row_var):
    """A trail of 0.45 sigma at its centre and 2 px sigma across a 256^2 frame: ~140 of chi2 (the exact sum of its
    square, the independent reference), 0.4 sigma of the frame's chi2 excess (sqrt(2 n) = 362) and no compact
    feature, but ~7 sigma along its line, past the bar of every line searched: described as a streak at its angle,
    through its line, with its peak. With the model's row noise (ROW_VAR, 0.13 of the pixels' own variance) the
    search runs on the residual less its row means: the rows' offsets are lines too (the best line of the raw
    residual is a row, 18 sigma)."""
    from test_morphology_rows import OWN_VAR, ROW_VAR, _frame

    rv = ROW_VAR if row_var == "rows" else row_var
    sig = math.sqrt(OWN_VAR)
    (x0, y0), (x1, y1) = (30, 20), (120, 240)
    trail = _trail((256, 256), (x0, y0), (x1, y1), 2.0, 0.45 * sig)
    assert 100 < float(np.sum(trail ** 2)) / OWN_VAR < 200
    res = _frame(0, row_var=rv, extra=trail)
    m = describe(res)
    assert m["significant"] and m["geometry"][0] == "streak", m["explanation"]
    assert m["empirical"] is not None and m["empirical"].get("form") == "streak"
    angle = math.degrees(math.atan2(y1 - y0, x1 - x0))
    got = float(m["explanation"].split(" px long at ")[1].split(" deg")[0])
    assert abs(got - angle) <= 1.0, m["explanation"]
    through = m["explanation"].split("through (x, y) = (")[1].split(")")[0]
    xt, yt = (float(v) for v in through.split(","))
    dist = abs((xt - x0) * (y1 - y0) - (yt - y0) * (x1 - x0)) / math.hypot(x1 - x0, y1 - y0)
    assert dist < 2.0, (through, dist)
    assert m["amplitude"] / res.gain == pytest.approx(0.45 * sig, rel=0.25)  # [ADU]: a 1 px profile's noise


@pytest.mark.parametrize("row_var", [1e-9, "rows"])
def test_null_frames_have_no_streak(row_var):
    """Ten null frames, without and with the model's row noise: no streak, and nothing significant."""
    from test_morphology_rows import ROW_VAR, _frame

    rv = ROW_VAR if row_var == "rows" else row_var
    for seed in range(10):
        m = describe(_frame(100 + seed, row_var=rv))
        assert not m["significant"], (seed, m["explanation"])


def test_one_bright_row_is_left_to_the_row_family():
    """One row 0.8 sigma high: a line along a pixel axis (0.8 x 256 / sqrt(1.5 x 256) = 10.5 sigma less its flanks'
    noise), the best of the line search, is not described as a streak: the row family's statistics judge a row."""
    from detector.morphology import along_pixel_axis
    from test_morphology_rows import OWN_VAR, _frame

    shape = (256, 256)
    r = np.random.default_rng(8).standard_normal(shape)
    r[100, :] += 0.8
    line = straight_line(r, np.ones(shape))
    assert is_streak(line) and along_pixel_axis(line)
    extra = np.zeros(shape)
    extra[100, :] = 0.8 * math.sqrt(OWN_VAR)
    m = describe(_frame(9, row_var=1e-9, extra=extra))
    assert "streak" not in m["geometry"], m["explanation"]


def test_a_series_worst_frame_counts_every_frames_trials():
    """A series' morphology is its worst frame's: the bars whose level is a false-alarm rate count the trials of all
    its frames (the best of k frames' n lines passes the bar of k n lines once in 1 / FRAME_FALSE_ALARM series; the
    same for the periodogram's bins), so a series of five is no more often flagged than one frame."""
    from detector.morphology import periodic_bar, periodic_contrast, tested_frequencies

    assert streak_bar(274320, 5) == pytest.approx(streak_bar(5 * 274320))
    assert streak_bar(274320, 5) > streak_bar(274320) + 0.2
    shape = (192, 192)
    assert periodic_bar(shape, 5) == pytest.approx(periodic_contrast(5 * tested_frequencies(shape)))
    assert periodic_bar(shape, 5) - periodic_bar(shape) == pytest.approx(math.log2(5))



@pytest.mark.parametrize("dof", [2.0, 3.0])
def test_a_heavy_tailed_scatter_makes_no_streak(dof):
    """White noise of a heavy-tailed law (Student t, a DSNU's or hot pixels' tails; scaled to a unit robust
    variance): line sums of such pixels scatter more than the normal law the bar assumes, and the raw map's best
    line passes it in most of twelve frames. The search's map (:func:`detector.morphology._line_search_map`: clipped
    at DETECTION_SIGMA of the robust scale, then scaled to the clipped values' variance) passes it in none; on
    normal noise it changes nothing (the bar's own rate, test_white_noise_stays_below_the_bar)."""
    from detector.morphology import _line_search_map, along_pixel_axis

    w = np.ones((256, 256))
    raw = searched = 0
    for seed in range(12):
        z = np.random.default_rng(300 + seed).standard_t(dof, w.shape)
        z /= math.sqrt(float(np.median(z * z)) / 0.4549)
        a, b = straight_line(z, w), straight_line(_line_search_map(z, w, 0.0), w)
        raw += is_streak(a) and not along_pixel_axis(a)
        searched += is_streak(b) and not along_pixel_axis(b)
    assert raw >= 4 and searched == 0, (raw, searched)
    g = np.random.default_rng(9).standard_normal(w.shape)
    assert np.allclose(_line_search_map(g, w, 0.0), g, atol=0.03 * np.abs(g).max())
